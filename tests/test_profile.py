"""`flightsim profile`: the records it writes and the observations it draws from them."""
import json

from flightsim.studies.profile import profile_workload, run_profile
from flightsim.studies.profile_report import observations


def _record(kernels, wall=1.0, idle=0.0):
    return {"workload": "w", "profiled_wall_s": wall, "idle_s": idle, "kernels": kernels}


def test_observations_name_the_dominant_kernel_idle_time_low_occupancy_and_spills():
    kernels = {"trace": {"gpu_s": 0.6, "occupancy": 0.25, "registers": 128, "local_bytes": 64},
               "tiny": {"gpu_s": 0.01, "occupancy": 0.1, "local_bytes": 8}}
    notes = observations(_record(kernels, idle=0.3))
    assert notes[0] == "`trace` takes 60% of the wall time"
    assert "the GPU idles 30% of the wall time (host work, launch gaps, syncs)" in notes
    assert "`trace` (60%) runs at 25% theoretical occupancy (128 registers/thread)" in notes
    assert "`trace` spills 64 bytes/thread to local memory" in notes
    assert not any("tiny" in note for note in notes)  # under 5 % of the wall: not worth a line


def test_observations_stay_quiet_on_a_busy_well_occupied_kernel():
    notes = observations(_record({"k": {"gpu_s": 0.9, "occupancy": 1.0, "local_bytes": 0}}, idle=0.05))
    assert notes == ["`k` takes 90% of the wall time"]


def test_profile_counts_the_beams_the_flight_fires(tmp_path):
    record = profile_workload("risley3", "cpu", quick=True)
    # the quick risley3 workload asks for 2e6 beams: round(2e6 / (5 kHz × 9 beams × 10 s)) = 4 lines of 10 s,
    # 1.8e6 beams, give or take a pulse at each line's ends
    assert record["unit"] == "beams" and abs(record["units"] - 4 * 10.0 * 5000 * 9) <= 4 * 2 * 9
    assert record["units"] % 9 == 0
    assert abs(record["rate"] * record["wall_s"] - record["units"]) < 1e-6 * record["units"]
    assert record["bare_rays_per_s"] > 0 and record["ratio_to_bare"] == record["rate"] / record["bare_rays_per_s"]


def test_run_profile_writes_json_and_markdown(tmp_path):
    run_profile("cpu", True, tmp_path, ("waveform_slope",))
    saved = json.loads((tmp_path / "profile.json").read_text())
    assert [w["workload"] for w in saved["workloads"]] == ["waveform_slope"]
    assert "| waveform_slope |" in (tmp_path / "profile.md").read_text()


def test_timeline_marks_each_event_once(tmp_path, monkeypatch):
    from flightsim.core import timeline

    path = tmp_path / "timeline.txt"
    monkeypatch.setenv("FLIGHTSIM_TIMELINE", str(path))
    monkeypatch.setattr(timeline, "_marked", set())
    timeline.mark("first_ray")
    timeline.mark("first_ray")
    timeline.mark("cli")
    events = [line.split()[0] for line in path.read_text().splitlines()]
    assert events == ["first_ray", "cli"]
    monkeypatch.delenv("FLIGHTSIM_TIMELINE")
    timeline.mark("exit")  # without the variable nothing is written
    assert len(path.read_text().splitlines()) == 2


NCU_CSV = '''==PROF== Connected to process 1234
"ID","Process ID","Process Name","Host Name","Kernel Name","Context","Stream","Block Size","Grid Size","Device","CC","dram__bytes.sum","gpu__time_duration.sum","sm__warps_active.avg.pct_of_peak_sustained_active","smsp__thread_inst_executed_per_inst_executed.ratio","l1tex__t_sectors_pipe_lsu_mem_global_op_ld.sum","l1tex__t_requests_pipe_lsu_mem_global_op_ld.sum"
"","","","","","","","","","","","byte","nsecond","%","","sector",""
"0","1234","python3","host","records_kernel__locals__trace_records_1a2b3c4_cuda_kernel_forward","1","7","(256, 1, 1)","(100, 1, 1)","0","9.0","2,000,000","1,000","40.0","30.0","1,000","250"
"1","1234","python3","host","records_kernel__locals__trace_records_1a2b3c4_cuda_kernel_forward","1","7","(256, 1, 1)","(100, 1, 1)","0","9.0","4,000,000","1,000","50.0","28.0","3,000","250"
"2","1234","python3","host","pulse_poses_9f8e7d6_cuda_kernel_forward","1","7","(256, 1, 1)","(4, 1, 1)","0","9.0","1000","500","20.0","32.0","0","0"
'''


def test_ncu_csv_is_averaged_per_kernel_under_our_names():
    from flightsim.studies.profile_ncu import parse

    kernels = parse(NCU_CSV)
    assert set(kernels) == {"trace_records", "pulse_poses"}
    trace = kernels["trace_records"]
    assert trace["launches"] == 2
    assert trace["achieved_occupancy_pct"] == 45.0 and trace["threads_per_warp_instruction"] == 29.0
    assert trace["dram_gb_per_s"] == 3000.0  # 3e6 bytes in 1 µs on average: 3 TB/s
    assert trace["dram_pct_of_peak"] is None  # not in this CSV
    assert kernels["pulse_poses"]["dram_gb_per_s"] == 2.0  # 1000 bytes in 500 ns
    assert trace["sectors_per_request"] == 8.0  # 2000 sectors over 250 requests on average
    assert "sectors_per_request" not in kernels["pulse_poses"]  # no global loads: no ratio


def test_only_the_metrics_ncu_lists_are_asked_for():
    from flightsim.studies.profile_ncu import known

    listing = """Device NVIDIA H100 80GB HBM3 (GH100)
Metric Name                      Metric Description
dram__bytes                      # of bytes accessed in DRAM
sm__warps_active                 cumulative # of warps in flight
"""
    asked = ["dram__bytes.sum", "sm__pipe_fp64_cycles_active.avg.pct_of_peak_sustained_active",
             "sm__warps_active.avg.pct_of_peak_sustained_active"]
    assert known(asked, listing) == ["dram__bytes.sum", "sm__warps_active.avg.pct_of_peak_sustained_active"]
    assert known(asked, "") == asked  # the query failed: ask for all, ncu names what it does not know


def test_a_second_profile_keeps_the_other_workloads_records(tmp_path):
    run_profile("cpu", True, tmp_path, ("waveform_slope",))
    run_profile("cpu", True, tmp_path, ("risley3",))
    saved = json.loads((tmp_path / "profile.json").read_text())
    assert [w["workload"] for w in saved["workloads"]] == ["risley3", "waveform_slope"]  # in WORKLOADS order


def test_ptxas_report_read_per_kernel():
    from flightsim.studies.kernel_resources import parse_ptxas

    report = """ptxas info    : Compiling entry function 'helper_cuda_kernel_backward' for 'sm_90'
ptxas info    : Function properties for helper_cuda_kernel_backward
    0 bytes stack frame, 0 bytes spill stores, 0 bytes spill loads
ptxas info    : Used 12 registers, used 0 barriers
ptxas info    : Compiling entry function 'records_kernel__locals__trace_records_e84d2437_cuda_kernel_forward' for 'sm_90'
ptxas info    : Function properties for records_kernel__locals__trace_records_e84d2437_cuda_kernel_forward
    432 bytes stack frame, 156 bytes spill stores, 248 bytes spill loads
ptxas info    : Used 64 registers, used 0 barriers, 432 bytes cumulative stack size, 33792 bytes smem
ptxas info    : Compiling entry function 'canopy_points_kernel__locals__trace_canopy_points_24d91470_cuda_kernel_forward' for 'sm_90'
ptxas info    : Function properties for canopy_points_kernel__locals__trace_canopy_points_24d91470_cuda_kernel_forward
    0 bytes stack frame, 0 bytes spill stores, -4 bytes spill loads
ptxas info    : Used 64 registers, used 0 barriers, 18432 bytes smem
"""
    assert parse_ptxas(report) == {
        "records_kernel__locals__trace_records_e84d2437_cuda_kernel_forward": {
            "frame": 432, "spill_stores": 156, "spill_loads": 248, "registers": 64, "smem": 33792},
        "canopy_points_kernel__locals__trace_canopy_points_24d91470_cuda_kernel_forward": {  # spilling to shared memory
            "frame": 0, "spill_stores": 0, "spill_loads": -4, "registers": 64, "smem": 18432}}


def test_sass_listing_counted_per_function():
    """cuobjdump -sass's listing (abridged from reduce_records and a kernel spilling): instructions, selects and
    local-memory accesses per function; the encodings' comment lines and predicates are not instructions."""
    from flightsim.studies.kernel_resources import parse_sass

    listing = """
\tcode for sm_90
\t\tFunction : reduce_records_e046634c_cuda_kernel_forward
\t.headerflags\t@"EF_CUDA_SM90 EF_CUDA_VIRTUAL_SM(EF_CUDA_SM90)"
        /*0000*/                   LDC R1, c[0x0][0x28] ;                 /* 0x00000a00ff017b82 */
                                                                          /* 0x000fe20000000800 */
        /*2160*/              @!P4 IMAD.MOV.U32 R60, RZ, RZ, R6 ;         /* 0x000000ffff3cc224 */
        /*21d0*/                   FSEL R64, R22, RZ, !P4 ;               /* 0x000000ff16407208 */
        /*2540*/                   SEL R106, R29, R102, !P3 ;             /* 0x000000661d6a7207 */
        /*2550*/               @P0 BRA 0x1060 ;                           /* 0x0000000000500947 */
        /*2560*/                   EXIT ;                                 /* 0x000000000000794d */
\t\t..........

\t\tFunction : trace_records_6b2f4723_cuda_kernel_forward
        /*0000*/                   STL [R1+0x8], R4 ;                     /* 0x0000080401007387 */
        /*0010*/              @!UP0 LDL.64 R2, [R1+0x10] ;               /* 0x0000100001027983 */
        /*0020*/                   FSETP.GEU.AND P0, PT, R2, RZ, PT ;     /* 0x000000ff0200720b */
"""
    assert parse_sass(listing) == {
        "reduce_records_e046634c_cuda_kernel_forward": {"instructions": 6, "selects": 2, "local": 0},
        "trace_records_6b2f4723_cuda_kernel_forward": {"instructions": 3, "selects": 0, "local": 2}}


def test_native_timing_brackets_each_sort_and_scan_and_restores_them(monkeypatch):
    """Warp's sort and scan primitives launch CUB kernels its activity timing does not see: within native_timing
    each call is bracketed by two events (stubbed here: no GPU) and runs as before; afterwards the primitives are
    Warp's own again."""
    import numpy as np
    import warp as wp

    from flightsim.studies.profile import NATIVE, native_timing

    recorded = []
    monkeypatch.setattr(wp, "Event", lambda device, enable_timing: object())
    monkeypatch.setattr(wp, "record_event", lambda event: recorded.append(event))
    originals = {name: getattr(wp.utils, name) for name in NATIVE}
    values = wp.array(np.array([3, 1, 2], dtype=np.int32), device="cpu")
    out = wp.empty(3, dtype=wp.int32, device="cpu")
    with native_timing("cpu") as spans:
        wp.utils.array_scan(values, out, inclusive=True)
        wp.utils.array_scan(values, out, inclusive=False)
    assert [name for name, _, _ in spans] == ["array_scan", "array_scan"] and len(recorded) == 4
    assert [(start, end) for _, start, end in spans] == [tuple(recorded[0:2]), tuple(recorded[2:4])]
    assert out.numpy().tolist() == [0, 3, 4]
    assert all(getattr(wp.utils, name) is primitive for name, primitive in originals.items())
