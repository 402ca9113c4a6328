"""Fixtures shared by the tests."""

import pytest
import torch


@pytest.fixture
def one_thread():
    """One intra-op thread: on tiny tensors more threads only contend (DESIGN section 6)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
