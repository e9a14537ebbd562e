"""The spherical parametrization of a genus-0 mesh (read by :mod:`elastic_jax.io`)."""
