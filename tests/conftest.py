import pytest
import torch


@pytest.fixture(autouse=True)
def _single_thread():
    # Small tensors: thread start-up costs more than it saves on a 2-core machine.
    torch.set_num_threads(1)
    yield


def torch_engine_agreement(task_class, theta, starts, returns) -> list[float]:
    """For a control task (cart-pole, mountain car): the fraction of ``returns`` (its Python
    episodes') that its batched torch rollout reproduces, in float32 and in float64."""
    fractions = []
    for dtype in (torch.float32, torch.float64):
        batched = task_class(engine="torch", dtype=dtype).evaluate(
            theta.to(dtype), initial_state=starts.to(dtype)
        )
        fractions.append(float((batched.float() == returns).float().mean()))
    return fractions
