"""The runtime: atomic writes, the compilation and export caches, the Dask pool.

It imports no shape analysis: the pool gets its task functions passed in.
"""
