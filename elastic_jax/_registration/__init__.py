"""Geodesics modulo reparametrization and rigid motion (paper 4.2-4.3, math §6, 7, 9):
the problem record, one module per phase of the solve, the phases chained
(``phases.py``), a solve on one grid (``one_grid.py``), levels of grids (``levels.py``)
and the public driver (``shape.py``).
"""
