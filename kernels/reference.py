"""The float64 reference of the per-beam pipeline, for measuring what each speed knob costs in accuracy.

For returns found by a production run (pulse, beam, face), it redoes every step in float64 with
the same device functions: DOE direction, wedge, sensor→local rotation, intersection with the hit
triangle's plane (float64 vertices) and both georeferencing models.
"""
import warp as wp

from kernels.frames import PulsePose64
from kernels.optics import doe_direction, prism_exit, rigid_array_direction
from kernels.wedge import Prism

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


@wp.kernel
def reference_returns(
    # In: the returns to redo
    poses: wp.array(dtype=PulsePose64),
    pose_index: wp.array(dtype=wp.int32),  # index into poses of each return
    beam: wp.array(dtype=wp.int32),  # i·n + j
    face: wp.array(dtype=wp.int32),  # triangle the production run hit
    # In: scene and instrument
    vertices: wp.array(dtype=wp.vec3d),  # [m, local]
    indices: wp.array(dtype=wp.int32),  # 3 per triangle
    n: int,
    spacing: wp.float64,  # [rad]
    truth: Prism,
    believed: Prism,
    # Out:
    true_points: wp.array(dtype=wp.vec3d),  # [m, local]
    exact_points: wp.array(dtype=wp.vec3d),
    nominal_points: wp.array(dtype=wp.vec3d),
    origins: wp.array(dtype=wp.vec3d),  # sensor origin of the pulse [m, local]
):
    k = wp.tid()
    pose = poses[pose_index[k]]
    b = beam[k]
    s1 = doe_direction(b // n, b % n, n, spacing)
    s3, exit_point, ok = prism_exit(s1, pose.phi, truth.n_glass, truth.apex, truth.thickness)
    start = pose.origin + pose.rot * exit_point
    direction = pose.rot * s3
    f = face[k]
    v0 = vertices[indices[3 * f]]
    normal = wp.cross(vertices[indices[3 * f + 1]] - v0, vertices[indices[3 * f + 2]] - v0)
    r = wp.dot(normal, v0 - start) / wp.dot(normal, direction)
    true_points[k] = start + r * direction
    s3b, exit_b, ok_b = prism_exit(s1, pose.phi, believed.n_glass, believed.apex, believed.thickness)
    exact_points[k] = pose.origin + pose.rot * (exit_b + r * s3b)
    axis = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(1.0))
    s3c, exit_c, ok_c = prism_exit(axis, pose.phi, believed.n_glass, believed.apex, believed.thickness)
    nominal_points[k] = pose.origin + pose.rot * (exit_c + r * rigid_array_direction(s1, s3c))
    origins[k] = pose.origin
