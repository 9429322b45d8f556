"""The generated configuration reference: it matches the models, and every key says what it is."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from pydantic import BaseModel, Field
from typer.testing import CliRunner

from mrslam import configdoc
from mrslam.cli import app

DOC = Path(__file__).resolve().parents[1] / "docs" / "config.md"


def test_committed_reference_is_the_generated_one() -> None:
    assert DOC.read_text() == configdoc.render_reference(), (
        f"docs/config.md is stale: regenerate it with `{configdoc.COMMAND}`")


@pytest.mark.parametrize("component", list(configdoc.COMPONENTS))
def test_every_key_has_a_description(component: str) -> None:
    missing = [r.key for s in configdoc.sections(configdoc.model_of(component))
               for r in s.rows if not r.description]
    assert not missing, f"{component}: no Field(description=...) for {', '.join(missing)}"


@pytest.mark.parametrize("component", list(configdoc.COMPONENTS))
def test_config_command_prints_defaults_that_load_back(component: str) -> None:
    res = CliRunner().invoke(app, ["config", component])
    assert res.exit_code == 0, res.output
    model = configdoc.model_of(component)
    assert model.model_validate(yaml.safe_load(res.stdout)) == model()


def test_config_command_markdown_and_bad_input() -> None:
    res = CliRunner().invoke(app, ["config", "--markdown"])
    assert res.exit_code == 0 and res.stdout == configdoc.render_reference()
    res = CliRunner().invoke(app, ["config", "sim", "--markdown"])
    assert res.stdout.startswith("## sim") and "`camera.spurious_rate`" in res.stdout
    for args in (["config"], ["config", "robot"]):
        res = CliRunner().invoke(app, args)
        assert res.exit_code == 2 and "server, agent, sim, demo" in res.output


class _Inner(BaseModel):
    """A nested section.

    Only its first paragraph is shown."""

    size_m: float = Field(1.0, gt=0, le=5, description="how big | how wide")
    mode: str = Field("a", description="which")


class _Outer(BaseModel):
    name: str | None = Field(None, description="a name")
    limit_m: float | None = Field(None, gt=0, description="a limit")
    inner: _Inner = _Inner(size_m=2.5)


def test_sections_take_defaults_from_the_parent_and_render_bounds() -> None:
    secs = list(configdoc.sections(_Outer))
    assert [s.path for s in secs] == ["", "inner"]
    assert secs[0].rows[0] == configdoc.Row("name", "str or null", "`null`", "a name")
    assert secs[0].rows[1].type == "float > 0 or null"   # the bound is the value's
    size = secs[1].rows[0]
    # the parent's default (2.5), not the class's (1.0); (0, 5] from gt and le
    assert (size.key, size.type, size.default) == ("inner.size_m", "float in (0, 5]", "`2.5`")
    assert secs[1].doc == "A nested section."
    text = configdoc.render_model("outer", "Intro.", _Outer)
    assert "### outer: `inner`" in text and "how big \\| how wide" in text


def test_unknown_component_is_a_user_error() -> None:
    with pytest.raises(configdoc.ConfigDocError, match="server, agent, sim, demo"):
        configdoc.model_of("robot")
