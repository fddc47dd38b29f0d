"""Benchmarks (python -m bench). Runs single-threaded BLAS unless told otherwise.

On the 2-core shared machines here a multi-threaded OpenBLAS fights other processes for the
cores: a 384x384 matmul measured 20 ms with 2 threads against 2.5 ms with one, so timings of
anything that reaches BLAS became noise. Pinocchio is single-threaded too. Set before numpy is
imported (python -m bench.X imports this package first); an explicit setting wins.
"""
import os

for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')
