"""benchmarks/bench_tensor_env.py: its steppers take the env options its figures compare."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_tensor_env  # noqa: E402
import peer_steppers  # noqa: E402


def test_the_action_check_figures_step_with_the_check_on_and_off():
    # The --checks-only figures time check_actions=True against False: both must step.
    for on in (True, False):
        step = bench_tensor_env.tensor_stepper(4, False, "cpu", check_actions=on)
        step()


def test_the_intersection_steps_in_cpp_beside_highway_env():
    bench_tensor_env.tensor_stepper(4, False, "cpu", "intersection-v0", native=True)()
    peer_steppers.highway_stepper("intersection-v0")()
