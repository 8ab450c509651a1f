"""Slow, obviously correct references of the exact signed distance to a closed triangle surface
(:mod:`muscle_mss.core.bones.triangle_distance`) and of pushing points out of it
(:func:`muscle_mss.core.bones.distance.push_out_of_bones`), for the tests only."""
import numpy as np

def reference_signed_distance(points, triangles, queries) -> np.ndarray:
    """Brute force: the distance to every triangle (projection on the plane when it falls inside
    the triangle, else the nearest point of the three edges), the smallest kept; inside where
    the generalized winding number (sum of the triangles' solid angles / 4 pi) exceeds 1/2.
    (q,) float64 mm, negative inside."""
    points = np.asarray(points, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    a, b, c = (points[triangles[:, k]] for k in range(3))
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    out = np.empty(len(queries))
    for q, x in enumerate(np.asarray(queries, dtype=np.float64)):
        height = np.einsum("ij,ij->i", x - a, normal)
        foot = x - height[:, None] * normal
        inside = np.ones(len(a), bool)
        for p0, p1 in ((a, b), (b, c), (c, a)):
            inside &= np.einsum("ij,ij->i", np.cross(p1 - p0, foot - p0), normal) >= 0
        best = np.where(inside, np.abs(height), np.inf)
        for p0, p1 in ((a, b), (b, c), (c, a)):
            edge = p1 - p0
            s = np.clip(np.einsum("ij,ij->i", x - p0, edge) / np.einsum("ij,ij->i", edge, edge),
                        0.0, 1.0)
            best = np.minimum(best, np.linalg.norm(x - (p0 + s[:, None] * edge), axis=1))
        ra, rb, rc = a - x, b - x, c - x
        la, lb, lc = (np.linalg.norm(r, axis=1) for r in (ra, rb, rc))
        numerator = np.einsum("ij,ij->i", ra, np.cross(rb, rc))
        denominator = (la * lb * lc + np.einsum("ij,ij->i", ra, rb) * lc
                       + np.einsum("ij,ij->i", rb, rc) * la + np.einsum("ij,ij->i", rc, ra) * lb)
        winding = np.sum(2.0 * np.arctan2(numerator, denominator)) / (4.0 * np.pi)
        out[q] = -best.min() if winding > 0.5 else best.min()
    return out


def reference_push_out(points, triangles, queries, radii) -> np.ndarray:
    """Brute force on the exact distance: each query moves to its nearest surface point plus
    ``radius`` along the outward direction there (the pseudo-normal's side), as often as it
    still lies closer than ``radius - 1e-9`` (at most 8 times). Rest frame, one bone; (q, 3)
    mm positions after the push."""
    points = np.asarray(points, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    out = np.array(queries, dtype=np.float64)
    for q in range(len(out)):
        for _ in range(8):
            d = reference_signed_distance(points, triangles, out[q:q + 1])[0]
            if d >= radii[q] - 1e-9:
                break
            h = 1e-5
            grad = np.array([(reference_signed_distance(points, triangles,
                                                        out[q:q + 1] + h * e)[0] - d) / h
                             for e in np.eye(3)])
            out[q] += (radii[q] - d) * grad / np.linalg.norm(grad)
    return out
