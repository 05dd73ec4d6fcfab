"""Ray–mesh hits beyond the float32 closest-hit cast (:mod:`kernels.mesh_cast`, Warp's mesh query): the fallback
cast through a BVH of slightly padded triangle boxes (for rays the float32 cast misses at shared edges and vertices),
and the hit refined in float64 on its triangle."""
import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


@wp.kernel
def corner_extent(
    points: wp.array(dtype=wp.vec3f),  # mesh vertices [m, local]
    indices: wp.array(dtype=wp.int32),  # 3 vertex indices per triangle
    extent: wp.array(dtype=wp.float32),  # in/out (1,): the largest |coordinate| of a triangle corner [m]
):
    """Grow ``extent[0]`` (start it at 0) to the largest absolute coordinate of any triangle's corners:
    the vertices the triangles use, not the unused ones."""
    t = wp.tid()
    largest = wp.float32(0.0)
    for k in range(3):
        p = points[indices[3 * t + k]]
        largest = wp.max(largest, wp.max(wp.abs(p[0]), wp.max(wp.abs(p[1]), wp.abs(p[2]))))
    wp.atomic_max(extent, 0, largest)


@wp.kernel
def padded_boxes(
    points: wp.array(dtype=wp.vec3f),  # mesh vertices [m, local]
    indices: wp.array(dtype=wp.int32),  # 3 vertex indices per triangle
    pad: wp.float32,  # margin added on every side [m]
    lowers: wp.array(dtype=wp.vec3f),  # out: per triangle, lower box corner [m]
    uppers: wp.array(dtype=wp.vec3f),  # out: per triangle, upper box corner [m]
):
    """The boxes of :func:`fallback_hit`'s BVH: each triangle's bounds widened by ``pad``."""
    t = wp.tid()
    a = points[indices[3 * t]]
    b = points[indices[3 * t + 1]]
    c = points[indices[3 * t + 2]]
    margin = wp.vec3f(pad, pad, pad)
    lowers[t] = wp.min(wp.min(a, b), c) - margin
    uppers[t] = wp.max(wp.max(a, b), c) + margin


@wp.func
def fallback_hit(bvh: wp.uint64, vertices: wp.array(dtype=wp.vec3d), indices: wp.array(dtype=wp.int32),
                  start: wp.vec3d, direction: wp.vec3d, max_range: wp.float32):
    """(face, t [m]) of the closest triangle on the ray, or (-1, max_range): a second look for rays the
    mesh query reports as misses.

    Warp's mesh BVH tests boxes without a margin, so a ray through an edge or vertex shared by
    flat triangles (boxes of zero thickness) can slip between them. Here the boxes are padded and
    each candidate gets an exact float64 ray–triangle test (Möller–Trumbore) that keeps the edges.
    """
    best_face = int(-1)
    best_t = wp.float64(max_range)
    query = wp.bvh_query_ray(bvh, wp.vec3f(start), wp.vec3f(direction))
    tri = int(0)
    while wp.bvh_query_next(query, tri, wp.float32(best_t) + 1.0):
        v0 = vertices[indices[3 * tri]]
        e1 = vertices[indices[3 * tri + 1]] - v0
        e2 = vertices[indices[3 * tri + 2]] - v0
        p = wp.cross(direction, e2)
        det = wp.dot(e1, p)
        if det != wp.float64(0.0):
            inv = wp.float64(1.0) / det
            d = start - v0
            u = wp.dot(d, p) * inv
            q = wp.cross(d, e1)
            v = wp.dot(direction, q) * inv
            t = wp.dot(e2, q) * inv
            eps = wp.float64(-1.0e-9)
            if u >= eps and v >= eps and u + v <= wp.float64(1.0) - eps and t >= wp.float64(0.0) and t < best_t:
                best_face = tri
                best_t = t
    return best_face, best_t


@wp.func
def refine_hit(vertices: wp.array(dtype=wp.vec3d), indices: wp.array(dtype=wp.int32), face: int,
                start: wp.vec3d, direction: wp.vec3d):
    """Distance along a float64 ray to the plane of a triangle given by float64 vertices [m]."""
    v0 = vertices[indices[3 * face]]
    normal = wp.cross(vertices[indices[3 * face + 1]] - v0, vertices[indices[3 * face + 2]] - v0)
    return wp.dot(normal, v0 - start) / wp.dot(normal, direction)
