"""Contacts: the collision spheres, the two collision structures (spatial hash, octree BVH) that
find overlapping spheres, the response to muscle-muscle and muscle-bone contacts, and the checks
of what overlap a solve leaves (spheres, surfaces)."""
