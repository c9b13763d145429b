"""Every bench records the processor its kernels were compiled for: absolute times compare only on the same one."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

from pathlib import Path

import pytest

from pidg.bench.provenance import machine, machine_line, vector_isa


def test_the_widest_enabled_vector_isa_is_named():
    assert vector_isa("+sse4.2,+avx,+avx2,-avx512f,-avx512bw") == "avx2"
    assert vector_isa("+avx512f,+avx2,+avx") == "avx512f"
    assert vector_isa("+neon,+fp-armv8") == "neon"
    assert vector_isa("-avx2,-avx,-sse4.2") is None


def _cpuinfo_flags() -> set[str]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return set()
    line = next((l for l in text.splitlines() if l.startswith("flags")), None)
    return set(line.split(":", 1)[1].split()) if line else set()


def test_machine_agrees_with_the_kernel_s_view_of_the_cpu():
    flags = _cpuinfo_flags()
    if "avx" not in flags:
        pytest.skip("no x86 flags in /proc/cpuinfo to compare with")
    here = machine()
    expected = "avx512f" if "avx512f" in flags else "avx2" if "avx2" in flags else "avx"
    assert here["vector_isa"] == expected
    assert here["cpu_model"] and here["cpu_target"] and here["cpus"] >= 1 and here["numba_threads"] >= 1
    line = machine_line(here, "abc123+dirty")
    assert here["cpu_model"] in line and here["cpu_target"] in line and expected in line and "abc123+dirty" in line
