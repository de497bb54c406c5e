"""The trajectory room: the rig's path through a recording, from its LiDAR sweeps and gyro.

`estimate` runs the trajectory pass (`run_trajectory_pass`: every sweep
through the `odometry` against a `local_map` of `voxel_hash` cells, knots
fitted in `odometry_kernels`) and chooses the GT method from it; `cache`
keeps a pass's result for the next run; `rig_trajectory` is the result, a
point's pose at its own time; `clouds` filters points and compensates a
sweep's motion with the gyro; `planes` fits local planes. Imports neither the
ground truth nor the run.
"""
