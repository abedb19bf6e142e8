"""The suite runs the libraries as the CLI does: BLAS on one thread (calib/parallel.py
single_blas; with OpenBLAS's default threads the MAP fits ran 3-6x slower on 2 cores)."""
from calib.parallel import single_blas

single_blas()
