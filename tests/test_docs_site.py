"""The Sphinx site of docs/ builds strictly (warnings are errors) and holds what it should.

The build runs once per session (about 15 s on 2 cores) into a temporary folder; the
expected content is read from the code and the YAML files here, independently of the
generator in docs/_ext/.
"""

import dataclasses
import html
import importlib
import re
import subprocess
import sys
import typing
from html.parser import HTMLParser
from pathlib import Path

import pytest
import yaml

pytest.importorskip("sphinx")
pytest.importorskip("myst_parser")

# Under pytest-xdist the file stays on one worker (--dist loadfile): the site is built once.

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ["envs", "branching", "objectives", "modules", "training", "distributed"]


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("docs_html")
    result = subprocess.run(
        [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-b", "html", "docs", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
    )
    log = result.stdout[-3000:] + result.stderr[-5000:]
    assert result.returncode == 0, f"strict docs build failed:\n{log}"
    assert "WARNING" not in result.stderr, log
    return out


def page_text(path: Path) -> str:
    """The page's text: tags removed, entities decoded."""
    return html.unescape(re.sub(r"<[^>]+>", "", path.read_text()))


class _Tables(HTMLParser):
    """Every table of a page: its classes and its rows of cell texts."""

    def __init__(self):
        super().__init__()
        self.tables: list[dict] = []
        self._cell: list[str] | None = None

    def handle_starttag(self, tag, attrs):
        if tag == "table":
            self.tables.append({"classes": dict(attrs).get("class", "").split(), "rows": []})
        elif tag == "tr" and self.tables:
            self.tables[-1]["rows"].append([])
        elif tag in ("td", "th") and self.tables:
            self._cell = []

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self.tables[-1]["rows"][-1].append(" ".join("".join(self._cell).split()))
            self._cell = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)


def tables(path: Path, css_class: str) -> list[list[list[str]]]:
    parser = _Tables()
    parser.feed(path.read_text())
    return [t["rows"] for t in parser.tables if css_class in t["classes"]]


def schema_row(site: Path, key: str, type_cell_start: str | None = None) -> list[str]:
    """The row of ``key`` in the config reference's schema tables (key, type, default, meaning)."""
    rows = [
        row
        for table in tables(site / "config_reference.html", "config-schema")
        for row in table[1:]
        if row[0] == key and (type_cell_start is None or row[1].startswith(type_cell_start))
    ]
    assert len(rows) == 1, f"{key}: {rows}"
    return rows[0]


def dataclass_default(cls, name):
    (f,) = [f for f in dataclasses.fields(cls) if f.name == name]
    return f.default if f.default is not dataclasses.MISSING else f.default_factory()


def yaml_comment(path: Path, key: str) -> str:
    (line,) = [line for line in path.read_text().splitlines() if line.startswith(f"{key}:")]
    return line.split("#", 1)[1].strip()


def test_site_pages_and_toctree(site):
    index = (site / "index.html").read_text()
    for page in [
        "quickstart",
        "concepts",
        "envs",
        "branching",
        "objectives",
        "training",
        "distributed",
        "results",
        "config_reference",
        "api/index",
    ]:
        assert (site / f"{page}.html").exists(), page
        assert f'href="{page}.html' in index, page


def test_quickstart_has_the_readme_commands(site):
    text = page_text(site / "quickstart.html")
    readme = (ROOT / "README.md").read_text().splitlines()
    commands = [line for line in readme if line.endswith(("# main job", "# tests"))]
    assert len(commands) == 2
    for command in commands:
        assert command in text


def test_api_pages_document_every_name_of_all(site):
    for name in PACKAGES:
        module = importlib.import_module(f"torchrl_grpo.{name}")
        page = (site / "api" / f"{name}.html").read_text()
        for public in module.__all__:
            assert f'id="torchrl_grpo.{name}.{public}"' in page, f"{name}.{public}"
    assert 'id="torchrl_grpo.objectives.GRPOLoss"' in (site / "api/objectives.html").read_text()
    envs = page_text(site / "api" / "envs.html")
    assert "HighwayEnv" in envs and "get_state" in envs


def test_config_reference_defaults_come_from_the_dataclasses(site):
    from torchrl_grpo.training import config

    for cls, key in [
        (config.GRPOConfig, "group_size"),
        (config.GRPOConfig, "clip_epsilon_low"),
        (config.GRPOConfig, "clip_epsilon_high"),
        (config.ExperimentConfig, "total_frames"),
        (config.OptimConfig, "max_grad_norm"),
    ]:
        default = dataclass_default(cls, key)
        _, type_cell, default_cell, _ = schema_row(site, key)
        assert default_cell == str(default), key
        assert type_cell == type(default).__name__, key

    # None, enums (with every choice listed), nested dataclasses.
    from torchrl_grpo.training.algos.grpo_config import TailPolicyName
    from torchrl_grpo.training.group_schemas import RayConfig

    assert schema_row(site, "replay_groups")[1:3] == ["int | None", "null"]
    tail = schema_row(site, "tail_policy")
    assert tail[2] == dataclass_default(config.GRPOConfig, "tail_policy").value
    assert all(member.value in tail[1] for member in TailPolicyName)
    num_actors = schema_row(site, "ray.num_actors")
    assert num_actors[2] == str(dataclass_default(RayConfig, "num_actors"))


def test_config_reference_meanings_and_options_come_from_the_yaml(site):
    conf = ROOT / "conf"
    assert schema_row(site, "group_size")[3] == yaml_comment(
        conf / "algo" / "grpo_branch.yaml", "group_size"
    )
    assert schema_row(site, "lr")[3] == yaml_comment(conf / "optim" / "adam.yaml", "lr")

    quick = yaml.safe_load((conf / "experiment" / "quick.yaml").read_text())
    (options,) = [
        t for t in tables(site / "config_reference.html", "config-options") if "quick" in t[0]
    ]
    column = options[0].index("quick")
    (row,) = [r for r in options if r[0] == "experiment.total_frames"]
    assert row[column] == str(quick["experiment"]["total_frames"])


def test_config_reference_lists_every_schema_key(site):
    from torchrl_grpo.training import config, group_schemas

    keys = {
        row[0]
        for table in tables(site / "config_reference.html", "config-schema")
        for row in table[1:]
    }
    schemas = [
        getattr(module, name)
        for module in (config, group_schemas)
        for name in module.__all__
        if dataclasses.is_dataclass(getattr(module, name))
    ]
    for schema in schemas:
        hints = typing.get_type_hints(schema)
        # A group field typed Any (Config.model) names its schema in its metadata.
        hints |= {f.name: f.metadata["schema"] for f in dataclasses.fields(schema) if f.metadata}
        prefix = "ray." if schema is group_schemas.RayConfig else ""
        for f in dataclasses.fields(schema):
            if schema in (config.Config, config.EvalConfig) and dataclasses.is_dataclass(
                hints[f.name]
            ):
                continue  # a config group: its keys are in the group's own table
            assert prefix + f.name in keys, f"{schema.__name__}.{f.name}"
