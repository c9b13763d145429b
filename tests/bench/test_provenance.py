"""Every bench records the processor its kernels were compiled for: absolute times compare only on the same one."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from pidg.bench.provenance import git_commit, machine, machine_line, vector_isa


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
    # the wait settings that pidg sets before torch loads (a kernel launch costs ~4 us or ~100 us by them)
    assert (here["omp_wait_policy"], here["gomp_spincount"]) == (os.environ["OMP_WAIT_POLICY"], os.environ["GOMP_SPINCOUNT"])
    assert f"OpenMP wait {here['omp_wait_policy']}, spin {here['gomp_spincount']}" in line


def _git(cwd: Path, *args: str) -> str:
    return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=cwd, check=True,
                          capture_output=True, text=True).stdout.strip()


@pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")
def test_the_commit_is_the_tracked_tree_s_and_an_untracked_copy_reports_none(tmp_path: Path):
    repo = tmp_path / "repo"
    (repo / "pidg").mkdir(parents=True)
    (repo / "pidg" / "__init__.py").write_text("")
    _git(repo, "init", "-q")
    _git(repo, "add", "pidg/__init__.py")
    _git(repo, "commit", "-q", "-m", "x")
    head = _git(repo, "rev-parse", "HEAD")
    assert git_commit(repo) == head
    (repo / "pidg" / "__init__.py").write_text("x = 1\n")
    assert git_commit(repo) == head + "+dirty"
    copy = repo / "old_build"  # an exported older tree inside the checkout (e.g. for an A/B run): not its commit
    (copy / "pidg").mkdir(parents=True)
    (copy / "pidg" / "__init__.py").write_text("")
    assert git_commit(copy) is None
    outside = tmp_path / "plain"
    (outside / "pidg").mkdir(parents=True)
    assert git_commit(outside) is None
