"""The trace kernels' two looks at a slot's ray.

The first look, over every slot, casts the ray with the float32 closest-hit cast (:func:`kernels.mesh_cast.closest_hit`:
Warp's mesh query, its per-ray work hoisted); a slot it misses (STATUS_RETRY) is listed.
The second look, over the listed slots only, casts them through the padded triangle boxes
(:func:`kernels.mesh_hits.fallback_hit`): rays the float32 query lets slip between flat triangles at a shared edge or
vertex, and true misses. The second look's code stays out of the kernel every slot runs, whose registers, and so
spills, are the fewer for it (ptxas, sm_90: the statistics trace kernel's spill stores 80 -> 56 B per thread;
profile-experiments.md section 20). The host launches both with :meth:`flightsim.engine.tracer.Tracer.launch_looks`.
"""
import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

FIRST_LOOK = 0  # a trace kernel's pass over every slot: the closest-hit cast; its misses are listed
SECOND_LOOK = 1  # ... over the listed slots only: the padded-box cast (mesh_hits.fallback_hit)
LOOKS = (FIRST_LOOK, SECOND_LOOK)


@wp.struct
class Misses:
    """The slots the first look's mesh query missed, for the second look: ``count[0]`` of them in ``slots``."""

    count: wp.array(dtype=wp.int32)
    slots: wp.array(dtype=wp.int32)


@wp.func
def list_miss(misses: Misses, slot: int):
    """List ``slot`` for the second look."""
    misses.slots[wp.atomic_add(misses.count, 0, 1)] = slot
