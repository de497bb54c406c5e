"""The run room: an ingest from the user's settings to the dataset on disk.

`settings` (as asked) and `resolved` (as decided once, after the trajectory
pass); `pipeline` orchestrates the passes: `plan` (the first pass and the
samples), the trajectory, `stream` (the jobs, in plan order); `sample` and
its `sample_job`, `sample_sparse`, `sample_dense`, `sample_parts` make one
sample in a worker; `summary` and `describe` say what was done
(`dataset.yaml`); `refine` and `timeshift` refine the rig's clocks and poses
from a recording first. Imports the trajectory and ground-truth rooms.
"""
