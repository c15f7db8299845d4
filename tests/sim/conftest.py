import pytest

from torchrl_grpo.envs import tensor_params


@pytest.fixture(scope="session")
def fast_params():
    return tensor_params("highway-fast-v0")


@pytest.fixture(scope="session")
def v0_params():
    return tensor_params("highway-v0", {"vehicles_count": 15})
