"""Bones: signed distance to each bone (sampled fields, exact distance to the triangles, their
on-disk store, the smooth lookup), bones as sets of spheres, and the nearest bones' weights for
the rigid pose."""
