"""Signed distance from points to a scene mesh (scoring of point clouds against the truth)."""
import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


@wp.kernel
def surface_distance(mesh: wp.uint64, points: wp.array(dtype=wp.vec3f), max_distance: float,
                     out: wp.array(dtype=wp.float32)):
    """Distance [m] from each point to the closest point of the mesh, signed by the side of the closest
    face (positive on the side its normal points to); NaN beyond ``max_distance``."""
    i = wp.tid()
    p = points[i]
    q = wp.mesh_query_point_no_sign(mesh, p, max_distance)
    if not q.result:
        out[i] = wp.nan
        return
    closest = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
    normal = wp.mesh_eval_face_normal(mesh, q.face)
    d = wp.length(p - closest)
    out[i] = wp.where(wp.dot(p - closest, normal) < 0.0, -d, d)
