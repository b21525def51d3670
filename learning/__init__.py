"""Offline learning of the chapter-7 policy: training data from recordings (dataset.py), the
denoising training (ours.py, train.py), the recipes of Table 7.1's rows (presets.py), the Table 7.1
distance (metrics.py) and the `xm train` / `xm simulate` commands (cli.py). Writes checkpoints
that services/policy loads; nothing here is imported by the node."""
