"""Properties of the build itself."""
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
