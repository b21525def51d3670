"""``xm``: the one command of the workcell. Subcommands live next to what they drive."""

from __future__ import annotations

import importlib
import sys

# subcommand -> (module:function taking argv, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "up": ("deploy.supervisor:up_main", "run a deployment: router + every service, restarts, logs"),
    "certs": ("deploy.certs:main", "certificates for a multi-host deployment's TLS links (docs/multihost.md)"),
    "status": ("deploy.supervisor:status_main", "list running services: pid, uptime, restarts, rates"),
    "graph": ("deploy.graph:main", "print a deployment's dataflow (edges, types, rates, queues), draw an SVG"),
    "recon": ("services.recon.cli:main", "reconstruct a recording offline (live stages + trajectory refinement)"),
    "record": ("services.recorder.cli:record_main", "record keys to an MCAP file"),
    "export": ("interop.cli:export_main", "export demonstrations: `xm export lerobot REC.mcap... -o DIR`"),
    "import": ("interop.cli:import_main", "import demonstrations: `xm import lerobot DIR`"),
    "replay": ("services.recorder.cli:replay_main", "republish an MCAP recording with original timing"),
    "train": ("learning.cli:train_main", "train the policy from recordings or teacher demos"),
    "simulate": ("learning.cli:simulate_main", "neural simulation of a trained policy"),
    "eval": ("evaluation.evaluate:main", "Table 7.1 evaluation against the baselines"),
    "glove": ("services.glove.cli:main", "glove tools: calibrate, register"),
    "robot": ("services.robot.cli:main", "robot tools: repeatability"),
    "calibrate": ("calibration.cli:main", "calibrate the camera rig with a ChArUco board (report beside the file)"),
    "detector": ("perception.cli:main", "2-D keypoint detector: label, train, eval"),
    "contactopt": ("contactopt.cli:main", "chapter-2 contact-based policy optimization: train, bench"),
    "skin": ("skin.cli:main", "sensor-skin design: layout on a mesh, unwrap, nesting, cutter SVGs, cell map"),
}


def usage() -> str:
    lines = ["usage: xm <command> [options]", "", "commands:"]
    lines += [f"  {name:<10} {text}" for name, (_, text) in COMMANDS.items()]
    lines += ["", "xm <command> --help for the options of one command."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(usage())
        return
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"xm: unknown command {name!r}\n\n{usage()}", file=sys.stderr)
        sys.exit(2)
    module, func = COMMANDS[name][0].split(":")
    try:
        entry = getattr(importlib.import_module(module), func)
    except (ImportError, AttributeError) as exc:
        print(f"xm {name}: not available in this build ({exc})", file=sys.stderr)
        sys.exit(2)
    result = entry(rest)
    if isinstance(result, int) and result:
        sys.exit(result)


if __name__ == "__main__":
    main()
