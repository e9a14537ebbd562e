"""Geodesics modulo reparametrization and rigid motion (paper 4.2-4.3, math §6, 7, 9):
the problem record, one module per phase of the solve, and the driver (``shape.py``).
"""
