"""The closest hit of a float32 ray on a Warp mesh: Warp's own BVH traversal and watertight triangle test
(``wp.mesh_query_ray``, Warp 1.19's mesh.h and intersect.h), with the test's per-ray work done once per ray.

Warp's query recomputes, for every triangle it tests, the ray's shear (the axis of its largest component and the
three ratios Sx, Sy, Sz of Woop, Benthin and Wald's watertight test, JCGT 2(1) 2013: two divisions and a reciprocal),
and it works out the hit's barycentrics, sign and normal, which flightsim never reads. Here the shear is computed once
per ray and each triangle test makes the same float32 operations on the same values in the same order, so the face
and t are Warp's bit for bit (the traversal, its nearer-child-first order and its stack of 32 nodes are Warp's, so
ties between triangles at one t resolve as Warp resolves them). An H100 casts 1.1-1.3× the rays per second of
``wp.mesh_query_ray`` with it through the GPU's default BVH (cubql, two triangles a leaf), up to 1.7× through BVHs of
larger leaves (profile-experiments.md section 41; ``python3 -m flightsim.studies.bvh_probe``). It reads Warp's BVH
and mesh structures directly, which is why pyproject.toml holds warp-lang to 1.19.x: a new Warp is checked against
``tests/test_mesh_cast.py`` before the bound moves.
"""
import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

_CLOSEST_HIT = r"""
    const wp::Mesh m = wp::mesh_get(mesh);
    int kz = wp::max_dim(direction);  // the shear of the watertight test, once per ray
    int kx = kz + 1;
    if (kx == 3) kx = 0;
    int ky = kx + 1;
    if (ky == 3) ky = 0;
    if (direction[kz] < 0.0f) { const int swap = kx; kx = ky; ky = swap; }
    const float Sx = direction[kx] / direction[kz];
    const float Sy = direction[ky] / direction[kz];
    const float Sz = 1.0f / direction[kz];
    auto pick = [](const wp::vec3& v, int k) { return k == 0 ? v[0] : (k == 1 ? v[1] : v[2]); };
    const wp::vec3 safe = wp::mesh_query_ray_safe_dir(direction);
    const wp::vec3 rcp_dir(1.0f / safe[0], 1.0f / safe[1], 1.0f / safe[2]);
    const bool fast_aabb = wp::mesh_query_ray_use_fast_aabb(direction);
    uint64_t stack[BVH_QUERY_STACK_SIZE];
    int stack_size = 0;
    uint64_t node = wp::bvh_query_node_load(m.bvh, *m.bvh.root);
    float min_t = max_t;
    int min_face = -1;
    while (true) {
        if (wp::bvh_query_node_is_leaf(node)) {
            const int end = wp::bvh_query_node_upper_payload(node);
            for (int pc = wp::bvh_query_node_lower_payload(node); pc < end; ++pc) {
                const int primitive = m.bvh.primitive_indices[pc];
                const wp::vec3 A = m.points[m.indices[primitive * 3 + 0]] - start;
                const wp::vec3 B = m.points[m.indices[primitive * 3 + 1]] - start;
                const wp::vec3 C = m.points[m.indices[primitive * 3 + 2]] - start;
                const float Akz = pick(A, kz), Bkz = pick(B, kz), Ckz = pick(C, kz);
                const float Ax = pick(A, kx) - Sx * Akz;
                const float Ay = pick(A, ky) - Sy * Akz;
                const float Bx = pick(B, kx) - Sx * Bkz;
                const float By = pick(B, ky) - Sy * Bkz;
                const float Cx = pick(C, kx) - Sx * Ckz;
                const float Cy = pick(C, ky) - Sy * Ckz;
                float U = wp::diff_product(Cx, By, Cy, Bx);
                float V = wp::diff_product(Ax, Cy, Ay, Cx);
                float W = wp::diff_product(Bx, Ay, By, Ax);
                if (U == 0.0f || V == 0.0f || W == 0.0f) {  // on an edge in float32: the products in float64
                    const double CxBy = (double)Cx * (double)By;
                    const double CyBx = (double)Cy * (double)Bx;
                    U = (float)(CxBy - CyBx);
                    const double AxCy = (double)Ax * (double)Cy;
                    const double AyCx = (double)Ay * (double)Cx;
                    V = (float)(AxCy - AyCx);
                    const double BxAy = (double)Bx * (double)Ay;
                    const double ByAx = (double)By * (double)Ax;
                    W = (float)(BxAy - ByAx);
                }
                if ((U < 0.0f || V < 0.0f || W < 0.0f) && (U > 0.0f || V > 0.0f || W > 0.0f))
                    continue;
                const float det = U + V + W;
                if (det == 0.0f)
                    continue;
                const float Az = Sz * Akz;
                const float Bz = Sz * Bkz;
                const float Cz = Sz * Ckz;
                const float T = U * Az + V * Bz + W * Cz;
                if (wp::xorf(T, wp::sign_mask(det)) < 0.0f)
                    continue;
                const float rcp_det = 1.0f / det;
                const float hit_t = T * rcp_det;
                if (hit_t < min_t && hit_t >= 0.0f) {
                    min_t = hit_t;
                    min_face = primitive;
                }
            }
        } else {  // both children tested, the nearer one taken, the other kept on the stack
            const int left = wp::bvh_query_node_lower_payload(node);
            const int right = wp::bvh_query_node_upper_payload(node);
            const wp::BVHPackedNodeHalf left_lower = wp::bvh_load_node(m.bvh.node_lowers, left);
            const wp::BVHPackedNodeHalf left_upper = wp::bvh_load_node(m.bvh.node_uppers, left);
            const wp::BVHPackedNodeHalf right_lower = wp::bvh_load_node(m.bvh.node_lowers, right);
            const wp::BVHPackedNodeHalf right_upper = wp::bvh_load_node(m.bvh.node_uppers, right);
            float t0 = FLT_MAX;
            float t1 = FLT_MAX;
            const bool h0 = wp::mesh_query_ray_intersect_aabb(start, direction, rcp_dir, fast_aabb,
                wp::vec3(left_lower.x, left_lower.y, left_lower.z),
                wp::vec3(left_upper.x, left_upper.y, left_upper.z), t0) && t0 < min_t;
            const bool h1 = wp::mesh_query_ray_intersect_aabb(start, direction, rcp_dir, fast_aabb,
                wp::vec3(right_lower.x, right_lower.y, right_lower.z),
                wp::vec3(right_upper.x, right_upper.y, right_upper.z), t1) && t1 < min_t;
            if (h0 && h1) {
                if (stack_size >= BVH_QUERY_STACK_SIZE)
                    break;
                const uint64_t left_node = wp::bvh_query_node_pack(left_lower, left_upper);
                const uint64_t right_node = wp::bvh_query_node_pack(right_lower, right_upper);
                const bool near_left = t0 < t1;
                stack[stack_size++] = near_left ? right_node : left_node;
                node = near_left ? left_node : right_node;
                continue;
            }
            if (h0 || h1) {
                node = h0 ? wp::bvh_query_node_pack(left_lower, left_upper)
                          : wp::bvh_query_node_pack(right_lower, right_upper);
                continue;
            }
        }
        if (stack_size == 0)
            break;
        node = stack[--stack_size];
    }
    face = min_face;
    t = min_t;
"""


@wp.func_native(_CLOSEST_HIT)
def _closest_hit(mesh: wp.uint64, start: wp.vec3f, direction: wp.vec3f, max_t: wp.float32, face: wp.ref[wp.int32],
                 t: wp.ref[wp.float32]): ...


@wp.func
def closest_hit(mesh: wp.uint64, start: wp.vec3f, direction: wp.vec3f, max_t: wp.float32):
    """(face, t) of the first triangle of ``mesh`` the ray ``start + t · direction`` meets with 0 ≤ t < ``max_t``
    (t in units of |direction|: metres for a unit direction); (−1, ``max_t``) when it meets none."""
    face = wp.int32(-1)
    t = max_t
    _closest_hit(mesh, start, direction, max_t, face, t)
    return face, t
