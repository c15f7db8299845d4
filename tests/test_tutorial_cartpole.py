"""The CartPole GRPO tutorial runs end to end in its quick mode and reports sane figures."""

import math
import subprocess
import sys
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tutorials" / "cartpole_grpo.py"
PICTURES = ("learning_curve.png", "group_branches.png")


def table_rows(stdout: str) -> dict[str, list[float]]:
    """The rows of the final table: ``{policy: [mean, min, max, frames, seconds]}``."""
    lines = stdout.splitlines()
    header = next(i for i, line in enumerate(lines) if line.startswith("policy") and "mean" in line)
    rows = {}
    for line in lines[header + 2 :]:  # skip the header and its rule
        fields = line.split()
        if len(fields) != 6:
            break
        rows[fields[0]] = [float(x) for x in fields[1:]]
    return rows


@pytest.mark.slow  # the default suite's 10-minute budget
def test_cartpole_tutorial_quick(tmp_path):
    result = subprocess.run(
        [sys.executable, str(SCRIPT), "--quick", "--out", str(tmp_path), "--seed", "0"],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert "final simulator state bitwise identical: True" in result.stdout

    for name in PICTURES:
        image = mpimg.imread(tmp_path / name)
        assert image.ndim == 3 and min(image.shape[:2]) > 100, (name, image.shape)
        pixels = image[..., :3].reshape(-1, 3)
        assert (pixels != pixels[0]).any(axis=1).mean() > 0.01, f"{name} is blank"
        assert len(np.unique(pixels, axis=0)) > 10, f"{name} has almost no colours"

    rows = table_rows(result.stdout)
    assert set(rows) == {"rule", "GRPO"}, result.stdout
    for name, numbers in rows.items():
        assert all(math.isfinite(x) for x in numbers), (name, numbers)
        assert 0 < numbers[0] <= 500, (name, numbers)
    assert rows["rule"][0] > 100  # a decent controller
    assert rows["GRPO"][3] > 0  # it trained on some frames
