"""Geodesics between parametrized surfaces and along them (paper Algorithm 1, math §7):
the solvers, the path solve, shooting, parallel transport, SRNF inversion.
"""
