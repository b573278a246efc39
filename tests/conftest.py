import pytest
import torch


@pytest.fixture(autouse=True)
def _single_thread():
    # Small tensors: thread start-up costs more than it saves on a 2-core machine.
    torch.set_num_threads(1)
    yield
