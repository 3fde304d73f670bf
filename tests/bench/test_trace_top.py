"""benchmarks/trace_top.py: device kernels summed from a hand-written profiler trace."""

import gzip
import json

from benchmarks import trace_top


def _trace() -> list[dict]:
    """Two device streams and a host process: only the device's kernels count."""
    return [
        {"ph": "M", "pid": 1, "name": "process_name", "args": {"name": "/device:GPU:0"}},
        {"ph": "M", "pid": 1, "tid": 7, "name": "thread_name", "args": {"name": "Stream #14"}},
        {"ph": "M", "pid": 1, "tid": 8, "name": "thread_name", "args": {"name": "Stream #72"}},
        {"ph": "M", "pid": 2, "name": "process_name", "args": {"name": "/host:CPU"}},
        {"ph": "X", "pid": 1, "tid": 7, "name": "nvjet_sm90_tst_128x160", "dur": 3000},
        {"ph": "X", "pid": 1, "tid": 7, "name": "nvjet_sm90_tst_128x160", "dur": 1000},
        {"ph": "X", "pid": 1, "tid": 8, "name": "loop_add_fusion", "dur": 500},
        {"ph": "X", "pid": 2, "tid": 1, "name": "loop_add_fusion", "dur": 99_000},  # host
        {"ph": "i", "pid": 1, "tid": 7, "name": "marker"},  # not a complete event
    ]


def test_device_kernels_sum_only_the_device_complete_events():
    time, calls, streams = trace_top.device_kernels(_trace())
    assert dict(time) == {"nvjet_sm90_tst_128x160": 4000, "loop_add_fusion": 500}
    assert dict(calls) == {"nvjet_sm90_tst_128x160": 2, "loop_add_fusion": 1}
    assert streams == {"Stream #14": 4000, "Stream #72": 500}


def test_matmul_kernels_are_told_from_fusions():
    assert trace_top.is_matmul("nvjet_sm90_tst_128x128_64x6_2x1_v_bz_NNT")
    assert trace_top.is_matmul("sm90_xmma_gemm_bf16bf16_bf16f32")
    assert trace_top.is_matmul("cutlass_80_tensorop_s1688gemm")
    assert not trace_top.is_matmul("input_add_reduce_fusion_1")
    assert not trace_top.is_matmul("loop_maximum_fusion_7")


def test_report_prints_the_matmul_share(tmp_path, capsys):
    path = tmp_path / "perfetto_trace.json.gz"
    with gzip.open(path, "wt") as f:
        json.dump({"traceEvents": _trace()}, f)
    trace_top.report(str(path), top=1)
    out = capsys.readouterr().out
    assert "kernels 4.5 ms: matmuls 4.0 ms (89%), other 0.5 ms" in out
    assert "4.00 ms      2 matmul nvjet_sm90_tst_128x160" in out
    assert "loop_add_fusion" not in out.split("other 0.5 ms")[1]  # (--top 1)
