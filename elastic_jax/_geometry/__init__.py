"""The geometry of one surface and of paths of surfaces on the spherical grid (math §1-6):
grid and quadrature, interpolation, spherical harmonics, the differential, the split
metric, the discrete path energy, the SRNF, SO(3), reparametrizations, validation, units.
"""
