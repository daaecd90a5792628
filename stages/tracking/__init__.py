"""Articulated tracking: the ellipsoid body, the EM fit of Horaud et al. 2009, initialisation, tracking."""
