"""The `sensorbox` command line (see `sensorbox.cli.main`).

numpy's OpenBLAS gets one thread per process unless the user says otherwise
(`OPENBLAS_NUM_THREADS`): this package is imported before numpy is, so the
setting takes. Our matrix products are small (points times 3x3, 12x12 normal
equations) and the parallelism is worker processes; BLAS threads only spun on
the other core (dense ingest of a full-resolution walk, 2 workers: 87.1 s ->
78.8 s; the odometry used 12.5 s of CPU for 4 s of data with them, 9.0 without).
"""

import os
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def run() -> None:
    """The `sensorbox` console script: `sensorbox.cli.main.main`, and Ctrl-C while its modules are still
    being imported (numpy, OpenCV, Open3D: about 2 s) as the same one line and exit code 130."""
    try:
        from sensorbox.cli.main import main
    except KeyboardInterrupt:
        sys.stderr.write("interrupted\n")
        raise SystemExit(130) from None
    main()
