"""Streaming: sources, conditioning, alignment, the pipeline loop, sinks, metrics, plots and the CLI.

The per-hop work is many small numpy operations; BLAS threads only add contention on small
matrices (measured: 10x slower at 16 channels on 2 busy cores), so the engine asks for one BLAS
thread unless the user set it. This must run before numpy is imported to take effect.
"""
import os as _os

for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")
