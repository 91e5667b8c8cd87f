"""Properties of the build itself."""
import platform
import re
import shutil
import subprocess

import pytest
import torch

import torchvor  # noqa: F401  (loads the extension)


def test_cpu_kernels_use_every_thread():
    """A CPU build without -fopenmp silently runs at::parallel_for on one thread."""
    threads = torch.get_num_threads()
    assert torch.ops.torchvor.cpu_threads_used() == threads


def test_cpu_kernels_follow_set_num_threads():
    previous = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        assert torch.ops.torchvor.cpu_threads_used() == 1
    finally:
        torch.set_num_threads(previous)


def test_cpu_isa_reported_and_forced_to_baseline(monkeypatch):
    """cpu_isa says which copy of the clip loop runs (csrc/cpu/isa.h)."""
    assert torch.ops.torchvor.cpu_isa() in ("avx2+fma", "baseline")
    monkeypatch.setenv("TORCHVOR_CPU_ISA", "baseline")
    assert torch.ops.torchvor.cpu_isa() == "baseline"


@pytest.mark.skipif(platform.machine() != "x86_64" or shutil.which("objdump") is None,
                    reason="needs x86-64 and objdump")
def test_avx_instructions_only_in_dispatched_functions():
    """The build targets baseline x86-64: AVX code may only sit in functions
    that run after a run-time CPU check (the clip loop's AVX2+FMA copy, the
    AVX2 and AVX-512 key and pair ranking of the kNN and its AVX2 candidate
    packs). Anywhere else, for example in an inline function compiled for
    AVX2 that the linker kept, it would crash older CPUs."""
    import torchvor._C as extension

    listing = subprocess.run(["objdump", "-d", "--no-show-raw-insn", "-C", extension.__file__],
                             check=True, capture_output=True, text=True).stdout
    allowed = re.compile(r"torchvor::cpu::run_avx2_fma<"
                         r"|torchvor::core::(key_ranks_avx2|key_ranks_avx512|pair_ranks|ranks_by_first_of_pairs)\("
                         r"|torchvor::core::offer_packs<")
    function, offenders = None, set()
    for line in listing.splitlines():
        header = re.match(r"^[0-9a-f]+ <(.*)>:$", line)
        if header:
            function = header.group(1)
        elif re.match(r"^\s+[0-9a-f]+:\s+v[a-z0-9]+\s", line) and not allowed.search(function or ""):
            offenders.add(function)
    assert not offenders, f"AVX (VEX-encoded) instructions outside the dispatched functions: {sorted(offenders)[:5]}"
