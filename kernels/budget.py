"""Error-budget reductions: per-slot float64 sums of the georeferencing deviation over Monte Carlo draws."""
import warp as wp

from kernels.trace import STATUS_RETURN

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


@wp.kernel
def accumulate_deviations(
    # In: one chunk of a points-mode trace
    status: wp.array(dtype=wp.int32),
    believed: wp.array(dtype=wp.vec3f),  # the processing's point [m, local]
    truth: wp.array(dtype=wp.vec3f),  # the true hit [m, local]
    base: int,  # run slot of the chunk's slot 0
    # In and out: per run slot
    sums: wp.array(dtype=wp.vec3d),  # Σ d, d = believed − truth [m]
    squares: wp.array(dtype=wp.vec3d),  # Σ d∘d [m²]
    hits: wp.array(dtype=wp.int32),  # draws in which the slot returned
):
    """Add one draw's deviation of every returning slot, one thread per slot."""
    i = wp.tid()
    if status[i] == STATUS_RETURN:
        d = wp.vec3d(believed[i]) - wp.vec3d(truth[i])
        sums[base + i] = sums[base + i] + d
        squares[base + i] = squares[base + i] + wp.cw_mul(d, d)
        hits[base + i] = hits[base + i] + 1
