"""The dashboard's teaching folders: a teaching session, its demonstrations, the library and review.

GUI callbacks run on viser's worker threads; they only issue recorder queries and hand reading,
scanning and decoding to one worker thread (``self.worker``), never to the panel's event loop. The
render loop calls ``review_frame`` each frame: it advances the scrubber and returns the replayed
messages that changed, which the panel draws with its live drawing code.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import viser
from viser import uplot

from services.panel import library, replay, view
from services.panel.library import OUTCOMES, SPLITS, DemoMeta, Entry, Library, MetaError
from shared.keys import CAMERAS, GLOVES

log = logging.getLogger("xm")
SCAN_PERIOD_S = 5.0  # the library notices recordings made elsewhere (xm record, another panel) this often
SPEEDS = ("0.25", "0.5", "1", "2", "4")
CAMERA_HZ = 5.0  # review camera views, composed on the worker
STRIP_WIDTH = 480


@dataclass
class TeachingSession:
    id: str
    task: str
    teacher: str
    glove_hand: str
    demos: int = 0
    executions: int = 0  # run from the Execute folder during the session
    successes: int = 0


@dataclass
class Review:
    entry: Entry
    timeline: replay.Timeline
    head: replay.Playhead
    steps: list[float]
    shown: dict[str, Any]  # the messages last handed to the drawing code, per stream
    last_tick: float
    last_cameras: float = 0.0
    cameras_of: tuple = ()  # the images and view choice the camera image shows
    strip_at: float = -1.0
    slider_at: float = 0.0  # the slider value the loop last wrote; the loop never writes over a person's move


class Teaching:
    """``recorder(verb, request)`` queries the recorder (blocking) and returns its replies;
    ``world_session()`` the newest Session message of the world, or None."""

    def __init__(self, server: viser.ViserServer, recordings: Path, recorder: Callable[[str, dict], list[dict]],
                 world_session: Callable[[], Any], count: Callable[[str], None]) -> None:
        self.server = server
        self.library = Library(recordings)
        self.recorder = recorder
        self.world_session = world_session
        self.count = count  # error counter in @health
        self.worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="panel-library")
        self.session: TeachingSession | None = None
        self.recording: Path | None = None  # the demonstration being recorded
        self.entries: list[Entry] = []
        self.review: Review | None = None
        self._scan: Future | None = None
        self._select: str | None = None  # a recording to pick once a scan lists it (the one just recorded)
        self._shown: tuple[str, str, str, str] | None = None  # the picked one's stored metadata, as put in the form
        self._last_scan = 0.0
        self._cameras: Future | None = None
        self._build()

    # --- layout ---------------------------------------------------------------------------------
    def _build(self) -> None:
        gui = self.server.gui
        with gui.add_folder("Teaching session"):
            self.task = gui.add_text("task", initial_value="")
            self.teacher = gui.add_text("teacher", initial_value="teacher")
            self.hand = gui.add_dropdown("glove hand", GLOVES, initial_value="right")
            gui.add_button("Start session").on_click(lambda _e: self._start_session())
            self.session_md = gui.add_markdown("no teaching session: recordings are stored without a label")
            self.next_label = gui.add_text("next label", initial_value="")
            self.layout = gui.add_text("start layout", initial_value="", hint="empty: the world's seed layout")
            gui.add_button("Start recording", color="red").on_click(lambda _e: self._start_recording())
            stops = gui.add_button_group("Stop recording", ("success", "failure", "unknown"))
            stops.on_click(lambda e: self._stop_recording(e.target.value))
            self.record_md = gui.add_markdown("not recording")
        with gui.add_folder("Demonstrations"):
            self.table_md = gui.add_markdown("reading the recordings directory...")
            self.pick = gui.add_dropdown("demonstration", ("-",), initial_value="-")
            self.pick.on_update(lambda _e: self._show_picked())
            self.label = gui.add_text("label", initial_value="")
            self.split = gui.add_dropdown("split", SPLITS, initial_value="train")
            self.outcome = gui.add_dropdown("outcome", OUTCOMES, initial_value="unknown")
            self.picked_layout = gui.add_text("layout", initial_value="")
            gui.add_button("Save").on_click(lambda _e: self._save())
            gui.add_button("Review").on_click(lambda _e: self._open_review())
            self.library_md = gui.add_markdown(f"directory `{self.library.directory}`")
        with gui.add_folder("Review") as self.review_folder:
            self.review_md = gui.add_markdown("pick a demonstration and press Review")
            self.strip = gui.add_image(np.full((28, STRIP_WIDTH, 3), 235, np.uint8), label="marks", format="png")
            self.time = gui.add_slider("time", min=0.0, max=1.0, step=0.01, initial_value=0.0, disabled=True)
            self.time.on_update(self._on_slider)
            controls = gui.add_button_group("playback", ("play", "pause", "<", ">"))
            controls.on_click(lambda e: self._control(e.target.value))
            self.speed = gui.add_dropdown("speed", SPEEDS, initial_value="1")
            self.speed.on_update(lambda _e: self._set_speed())
            trims = gui.add_button_group("trim", ("start here", "end here", "clear"))
            trims.on_click(lambda e: self._trim(e.target.value))
            self.view = gui.add_dropdown("cameras", ("grid", *CAMERAS), initial_value="grid")
            self.cameras = gui.add_image(np.full((120, 160, 3), 60, np.uint8), label="recorded views", format="jpeg")
            self.marks_md = gui.add_markdown("")
            self.plot: Any = None  # the signals of the reviewed demonstration (uPlot; legend entries toggle them)
            gui.add_button("Close review").on_click(lambda _e: self._close_review())

    def _submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        """Run ``fn`` on the worker; an exception it raises is counted, logged and shown, never lost."""
        future = self.worker.submit(fn, *args)
        future.add_done_callback(self._check)
        return future

    def _check(self, future: Future) -> None:
        exc = None if future.cancelled() else future.exception()
        if exc is not None:
            self.count("worker_error")
            log.warning("panel worker: %r", exc, exc_info=exc)
            self.library_md.content = f"**error**: {exc!r}"

    # --- teaching session ------------------------------------------------------------------------
    def offer_world_session(self, session: Any) -> None:
        """Fill task and glove hand from the world's label until the teacher starts a session."""
        if self.session is None and not self.task.value and getattr(session, "task", ""):
            self.task.value = session.task
            if session.tactile_hand in GLOVES:
                self.hand.value = session.tactile_hand

    def _start_session(self) -> None:
        task, teacher = self.task.value.strip(), self.teacher.value.strip()
        if not task or not teacher:
            self.session_md.content = "**error**: a teaching session needs a task and a teacher"
            return
        sid = f"{task}-{teacher}-{time.strftime('%Y%m%d-%H%M%S')}"
        self.session = TeachingSession(sid, task, teacher, self.hand.value)
        self._session_line()
        self.request_scan()

    def _session_line(self) -> None:
        s = self.session
        if s is not None:
            self.session_md.content = (f"session `{s.id}`: task **{s.task}**, teacher **{s.teacher}**, glove on the "
                                       f"{s.glove_hand} hand, {s.demos} demonstrations"
                                       + (f", {s.executions} execution{'s' * (s.executions != 1)} "
                                          f"({s.successes} succeeded)"
                                          if s.executions else ""))

    def context(self) -> dict:
        """The teaching session an execution runs in (empty without one)."""
        s = self.session
        return {} if s is None else {"session": s.id, "teacher": s.teacher, "task": s.task}

    def executed(self, success: bool) -> None:
        """An execution ended during the session: counted on its line."""
        if self.session is not None:
            self.session.executions += 1
            self.session.successes += int(success)
            self._session_line()

    def _start_recording(self) -> None:
        """With a session: a demonstration, named and labelled; without: a plain recording."""
        request: dict[str, Any] = {"keys": "xm/**"}
        path = None
        if self.session is not None:
            path = library.next_demo_path(self.library.directory.resolve(), self.session.task, self.session.teacher)
            request["path"] = str(path)
        self.record_md.content = "start: asking the recorder..."
        replies = self._ask("start", request)
        if replies is None:
            return
        self.record_md.content = view.recorder_text("start", replies)
        if path is None or not replies or not replies[0].get("ok"):
            return
        s = self.session
        world = self.world_session()
        layout = self.layout.value.strip() or (getattr(world, "seed_layout", "") if world is not None else "")
        meta = DemoMeta(label=self.next_label.value.strip() or f"{s.task} {s.demos + 1}", task=s.task,
                        teacher=s.teacher, glove_hand=s.glove_hand, layout=layout, session=s.id)
        try:
            library.write_meta(path, meta)
        except (MetaError, OSError) as exc:
            self.record_md.content += f"; **metadata not stored**: {exc}"
            self.count("library_error")
        self.recording = path
        self.next_label.value = ""  # the next demonstration gets its own label (or the default)
        s.demos += 1
        self._session_line()

    def _stop_recording(self, outcome: str) -> None:
        self.record_md.content = "stop: asking the recorder..."
        replies = self._ask("stop", {})
        if replies is None:
            return
        self.record_md.content = view.recorder_text("stop", replies)
        self.recording = None
        stopped = replies[0].get("path") if replies and replies[0].get("ok") else None
        # a demonstration has its metadata beside it (also one a restarted panel started): store the outcome
        if isinstance(stopped, str) and stopped.endswith(".mcap") and library.sidecar_path(stopped).exists():
            path = Path(stopped)
            self._select = path.name[:-len(".mcap")]
            self._submit(self._store_outcome, path, outcome)
        self.request_scan()

    def _store_outcome(self, path: Path, outcome: str) -> None:
        try:
            self.library.update(path, outcome=outcome)
        except (MetaError, OSError) as exc:
            self.library_md.content = f"**error**: {path.name}: {exc}"
            self.count("library_error")

    def _ask(self, verb: str, request: dict) -> list[dict] | None:
        try:
            return self.recorder(verb, request)
        except Exception as exc:  # a dead session or garbage reply: show it, keep the panel alive
            self.record_md.content = f"**error**: {exc!r}"
            return None

    # --- library ---------------------------------------------------------------------------------
    def tick(self, now: float) -> None:
        """Event loop, each frame while a browser is connected: rescan now and then (on the worker)."""
        if now - self._last_scan >= SCAN_PERIOD_S:
            self.request_scan(now)

    def request_scan(self, now: float | None = None) -> None:
        self._last_scan = time.monotonic() if now is None else now
        if self._scan is None or self._scan.done():
            self._scan = self._submit(self._do_scan)

    def _do_scan(self) -> None:
        try:
            entries = self.library.scan(task=self.session.task if self.session else None)
        except OSError as exc:
            self.library_md.content = f"**error** reading `{self.library.directory}`: {exc}"
            self.count("library_error")
            return
        self.entries = entries
        names = tuple(e.name for e in entries) or ("-",)
        if tuple(self.pick.options) != names:
            self.pick.options = names
        if self._select in names:
            self.pick.value, self._select = self._select, None
        elif self.pick.value not in names:
            self.pick.value = names[-1]
        selected = self.picked()
        # The picked demonstration's metadata changed on disk (the outcome stored at Stop, a save from
        # another browser): the form follows it, unless it holds edits not saved yet.
        if selected is not None and self._form() in (self._shown, _stored(selected)):
            self._show_picked()
        text = library.table(entries, selected.path if selected else None)
        if self.table_md.content != text:
            self.table_md.content = text
        trainable = sum(e.trainable for e in entries)
        validation = sum(e.usable and e.meta.split == "validation" for e in entries)
        line = (f"`{self.library.directory}`: {len(entries)} recordings, {trainable} for training, "
                f"{validation} for validation")
        if self.library_md.content != line:  # a rescan that finds nothing new sends nothing to the browsers
            self.library_md.content = line

    def picked(self) -> Entry | None:
        return next((e for e in self.entries if e.name == self.pick.value), None)

    def _show_picked(self) -> None:
        e = self.picked()
        if e is not None:
            self.label.value, self.split.value, self.outcome.value = e.meta.label, e.meta.split, e.meta.outcome
            self.picked_layout.value = e.meta.layout
            self._shown = _stored(e)

    def _form(self) -> tuple[str, str, str, str]:
        return self.label.value, self.split.value, self.outcome.value, self.picked_layout.value

    def _save(self) -> None:
        e = self.picked()
        if e is None:
            self.library_md.content = "**error**: no demonstration picked"
            return
        self._submit(self._do_save, e.path, {"label": self.label.value.strip(), "split": self.split.value,
                                                   "outcome": self.outcome.value,
                                                   "layout": self.picked_layout.value.strip()})

    def _do_save(self, path: Path, changes: dict) -> None:
        try:
            self.library.update(path, **changes)
        except (MetaError, OSError) as exc:
            self.library_md.content = f"**error**: {path.name}: {exc}"
            self.count("library_error")
            return
        self._do_scan()
        self.library_md.content += f"; saved `{path.name}`"

    # --- review ----------------------------------------------------------------------------------
    def _open_review(self) -> None:
        e = self.picked()
        if e is None:
            self.review_md.content = "**error**: no demonstration picked"
            return
        self.review_md.content = f"reading `{e.name}`..."
        self._submit(self._load, e)

    def _load(self, e: Entry) -> None:
        try:
            timeline = replay.load_timeline(e.path)
        except (replay.ReplayError, ValueError, OSError) as exc:
            self.review_md.content = f"**error**: {e.name}: {exc}"
            self.count("review_error")
            return
        lo, hi = e.meta.window(timeline.duration)
        head = replay.Playhead(lo, hi, lo, speed=float(self.speed.value))
        self.review = Review(e, timeline, head, timeline.step_times(), {}, time.monotonic(), slider_at=round(lo, 2))
        self.time.max = max(math.ceil(timeline.duration * 100) / 100, 0.01)  # the slider's 0.01 s steps
        self.time.disabled = False
        self.time.value = lo
        self.review_md.content = (f"reviewing **{e.name}** ({e.meta.label or 'no label'}), {timeline.duration:.1f} s, "
                                  f"kept {lo:.2f}-{hi:.2f} s")
        self.marks_md.content = "marks: red, keypoints unobserved; orange, glove frames lost. " + \
            replay.marks_text(timeline)
        self._plot(timeline)

    def _plot(self, timeline: replay.Timeline) -> None:
        t, series = replay.signals(timeline)
        if self.plot is not None:
            self.plot.remove()
            self.plot = None
        if not series:
            return
        colors = ("#dc2828", "#e6781e", "#1e64dc", "#3c9c3c")
        with self.review_folder:
            self.plot = self.server.gui.add_uplot(
                (t, *series.values()),
                (uplot.Series(label="s"), *(uplot.Series(label=name, stroke=colors[i % len(colors)], width=1.5)
                                            for i, name in enumerate(series))),
                title="signals", scales={"x": {"time": False}}, aspect=1.6)  # x: seconds into the recording

    def _close_review(self) -> None:
        self.review = None
        self.time.disabled = True
        self.review_md.content = "pick a demonstration and press Review"

    @property
    def reviewing(self) -> bool:
        return self.review is not None

    def health(self) -> dict:
        """@health extras: the library's size, the session and the label its next demonstration
        gets, and what is being reviewed."""
        r = self.review
        return {"recordings": len(self.entries), "trainable": sum(e.trainable for e in self.entries),
                "session": self.session.id if self.session else None,
                "next_label": self.next_label.value if self.session else None,
                "reviewing": None if r is None else {"name": r.entry.name, "at_s": round(r.head.position, 3),
                                                     "playing": r.head.playing}}

    async def _on_slider(self, event: Any) -> None:
        # A coroutine: viser awaits it right after storing the person's value, before the render loop
        # can write the playhead's position over it (a plain callback would run later, on a pool thread).
        r = self.review
        if r is not None and event.client is not None:  # a person moved it (the loop's own moves have none)
            r.head.playing = False
            r.head.seek(float(self.time.value))

    def _control(self, what: str) -> None:
        r = self.review
        if r is None:
            return
        if what == "play":
            if r.head.position >= r.head.end:
                r.head.seek(r.head.start)
            r.head.playing = True
        elif what == "pause":
            r.head.playing = False
        else:
            r.head.step(r.steps, +1 if what == ">" else -1)

    def _set_speed(self) -> None:
        if self.review is not None:
            self.review.head.speed = float(self.speed.value)

    def _trim(self, what: str) -> None:
        r = self.review
        if r is None:
            return
        pos, meta = r.head.position, r.entry.meta
        start, end = meta.trim_start_s, meta.trim_end_s
        if what == "start here":
            start = pos
        elif what == "end here":
            end = pos
        else:
            start, end = 0.0, None
        self._submit(self._do_trim, r, start, end)

    def _do_trim(self, r: Review, start: float, end: float | None) -> None:
        try:
            r.entry.meta = self.library.update(r.entry.path, trim_start_s=round(start, 3),
                                               trim_end_s=None if end is None else round(end, 3))
        except (MetaError, OSError) as exc:
            self.review_md.content = f"**error**: trim refused: {exc}"
            return
        lo, hi = r.entry.meta.window(r.timeline.duration)
        r.head.start, r.head.end = lo, hi
        r.head.seek(r.head.position)
        r.strip_at = -1.0
        self.review_md.content = f"reviewing **{r.entry.name}**, kept {lo:.2f}-{hi:.2f} s (the file is unchanged)"
        self._do_scan()

    def review_frame(self, now: float) -> dict[str, Any]:
        """Event loop: advance the scrubber; the replayed messages that changed since the last call."""
        r = self.review
        if r is None:
            return {}
        pos = r.head.advance(now - r.last_tick)
        r.last_tick = now
        if round(pos, 2) != r.slider_at:  # moved by playing, a step or a trim
            r.slider_at = self.time.value = round(pos, 2)
        frame = r.timeline.frame(pos)
        # camera images go to the recorded views (read and decoded on the worker), not to the live thumbnail
        changed = {k: m for k, m in frame.items() if r.shown.get(k) is not m and not k.startswith("image/")}
        r.shown.update(changed)
        if abs(r.strip_at - pos) > 1e-3:
            r.strip_at = pos
            self.strip.image = replay.timeline_strip(r.timeline, pos, (r.head.start, r.head.end), STRIP_WIDTH)
        if now - r.last_cameras >= 1.0 / CAMERA_HZ and (self._cameras is None or self._cameras.done()):
            images = {k.split("/", 1)[1]: m for k, m in frame.items() if k.startswith("image/")}
            shows = (self.view.value, *(id(m) for m in images.values()))
            if shows != r.cameras_of:
                r.last_cameras, r.cameras_of = now, shows
                self._cameras = self._submit(self._compose, images, self.view.value)
        return changed

    def _compose(self, images: dict[str, Any], view_choice: str) -> None:
        """Worker: read and decode the recorded JPEGs, show them as a grid or one camera, large."""
        if view_choice != "grid":
            images = {c: m for c, m in images.items() if c == view_choice}
        try:
            jpegs = replay.image_bytes(images)
        except Exception as exc:  # a segment deleted or damaged under the review: say so, keep going
            self.count("review_error")
            self.marks_md.content = f"**error** reading the recorded images: {exc!r}"
            return
        decoded = {c: replay.decode_jpeg(data) for c, data in jpegs.items()}
        if view_choice == "grid":
            img = replay.camera_grid(decoded)
        else:
            img = decoded.get(view_choice)
            if img is None:
                img = np.full((120, 160, 3), 60, np.uint8)
        self.cameras.image = img

    def close(self) -> None:
        self.worker.shutdown(wait=False, cancel_futures=True)


def _stored(e: Entry) -> tuple[str, str, str, str]:
    """A demonstration's editable metadata in the order of the form's fields."""
    return e.meta.label, e.meta.split, e.meta.outcome, e.meta.layout
