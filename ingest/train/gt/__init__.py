"""The ground-truth room: points to depth, from one window (sparse) or a whole trajectory (dense).

`groundtruth` is sparse GT's z-buffer and occlusion test; `dense`
accumulates, snaps and renders a window of points placed by the trajectory,
with the planes and free-space verdicts `block_planes` computes once per
point (`free_space`: what a later LiDAR slice saw through, a mover's earlier
positions); `align` and `align_check` lay a sample's points onto its image
and sum the samples up. Imports the trajectory room, never the run.
"""
