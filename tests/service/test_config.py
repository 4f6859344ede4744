"""The typed configuration (service/config.py): the [graph] section's tables reach the localizer's parameters,
each key of them; the flat [graph] keys from before the tables still load, with a warning per key."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import logging
import tomllib
import typing
from pathlib import Path

import pydantic
import pydantic_settings
import pytest

from macroloc.graph.errors import UserInputError
from macroloc.graph.keyframes import KeyframeRule
from macroloc.graph.params import IsamSettings, LocalizerParams
from macroloc.service.config import LEGACY_GRAPH_KEYS, GraphConfig, MacrolocConfig, load_config
from macroloc.service.localizer_loop import LoopSettings, settings_from_config

TABLES = [name for name, f in GraphConfig.model_fields.items() if dataclasses.is_dataclass(f.annotation)]


def _other(value: object) -> object:
    """A value of the same type as a default, different from it (and within every key's bounds)."""
    if isinstance(value, bool):
        return not value
    if isinstance(value, int):
        return value + 1
    if isinstance(value, tuple):  # one element changed: one leaf of the settings
        return (_other(value[0]), *value[1:])
    if isinstance(value, str):
        return value + "_other"
    assert isinstance(value, float)
    return value * 0.5 + 0.0625 if value <= 1.0 else value * 1.5 + 0.125  # fractions stay fractions


def _leaves(settings: LoopSettings) -> list[object]:
    def flat(x: object) -> list[object]:
        return [v for item in x for v in flat(item)] if isinstance(x, tuple) else [x]

    return flat(dataclasses.astuple(settings))


def _toml(value: object) -> str:
    return str(value).lower() if isinstance(value, bool) else repr(value)


def test_the_default_graph_section_is_the_components_defaults() -> None:
    """No key set: the localizer's, the keyframe rule's and iSAM2's own defaults, as before the tables."""
    s = settings_from_config(MacrolocConfig().graph)
    assert s == LoopSettings()
    assert s.localizer == LocalizerParams() and s.isam == IsamSettings(relinearize_threshold=0.01)
    assert s.rule == KeyframeRule(0.25, 0.15, 0.34, while_exploring=False, without_sightings_m=0.0)
    assert s.localizer.registration.inlier_threshold_m == 0.6 and s.storey_hint is None


def test_tables_are_named_as_the_components() -> None:
    """Each table but [graph.keyframes] and [graph.isam] is the `LocalizerParams` part of its name."""
    parts = {f.name for f in dataclasses.fields(LocalizerParams)}
    assert set(TABLES) - parts == {"keyframes", "isam"}


def test_every_table_of_the_graph_is_its_components_parameters() -> None:
    """Each `LocalizerParams` part, the `KeyframeRule` and `IsamSettings` is its table, of the same type and the
    same defaults (each key declared once, as the dataclass's field): nothing that changes the localizer's
    behaviour is out of the config's (and `dump-config`'s) reach."""
    graph = GraphConfig()
    for part in dataclasses.fields(LocalizerParams):
        assert getattr(graph, part.name) == getattr(LocalizerParams(), part.name), part.name
        assert type(getattr(graph, part.name)) is type(getattr(LocalizerParams(), part.name)), part.name
    assert type(graph.keyframes) is KeyframeRule and graph.keyframes == KeyframeRule()
    assert type(graph.isam) is IsamSettings and graph.isam == IsamSettings()


@pytest.mark.parametrize("table", TABLES)
def test_every_key_of_every_table_takes_effect(table: str) -> None:
    """Each key set to another value changes that one value of the session's settings, and it arrives under its
    own name (`[graph.judge] surface_margin` is `LocalizerParams.judge.surface_margin`)."""
    default = settings_from_config(GraphConfig())
    part = getattr(GraphConfig(), table)
    assert dataclasses.fields(part), table
    for key in (f.name for f in dataclasses.fields(part)):
        value = _other(getattr(part, key))
        s = settings_from_config(GraphConfig.model_validate({table: {key: value}}))
        if table == "keyframes":
            where = s.rule
        elif table == "isam":
            where = s.isam
        else:
            where = getattr(s.localizer, table)
        assert getattr(where, key) == value, f"[graph.{table}] {key}"
        changed = [i for i, (a, b) in enumerate(zip(_leaves(default), _leaves(s), strict=True)) if a != b]
        assert len(changed) == 1, f"[graph.{table}] {key} changed {len(changed)} values"


def test_a_nested_key_in_a_file_takes_effect(tmp_path: Path) -> None:
    path = tmp_path / "config.toml"
    path.write_text("[graph]\nstorey_hint = \"Level 2\"\n\n[graph.judge]\nsurface_margin = 0.2\n")
    s = settings_from_config(load_config(path).graph)
    assert s.localizer.judge.surface_margin == 0.2 and s.storey_hint == "Level 2"
    assert dataclasses.replace(s.localizer.judge, surface_margin=0.3) == LocalizerParams().judge


def test_a_flat_graph_file_loads_as_its_nested_equivalent_with_one_warning_per_key(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Every [graph] key from before the tables (e.g. `associate_m`, `registration_tolerance_m`) moves to its
    table: the same settings as the nested file, and one warning line naming the new key for each."""
    flat, nested = ["[graph]", "storey_hint = \"Level 1\""], {"graph": ["storey_hint = \"Level 1\""]}
    for old, (table, key) in LEGACY_GRAPH_KEYS.items():
        value = _toml(_other(getattr(getattr(GraphConfig(), table), key)))
        flat.append(f"{old} = {value}")
        nested.setdefault(f"graph.{table}", []).append(f"{key} = {value}")
    (tmp_path / "flat.toml").write_text("\n".join(flat) + "\n")
    (tmp_path / "nested.toml").write_text("".join(f"[{t}]\n" + "\n".join(lines) + "\n\n"
                                                  for t, lines in nested.items()))
    with caplog.at_level(logging.WARNING, logger="macroloc.service.config"):
        legacy = load_config(tmp_path / "flat.toml").graph
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="macroloc.service.config"):
        current = load_config(tmp_path / "nested.toml").graph
    assert not caplog.records  # the nested form warns of nothing
    assert legacy == current and settings_from_config(legacy) == settings_from_config(current)
    assert settings_from_config(current) != settings_from_config(GraphConfig())
    assert len(warnings) == len(LEGACY_GRAPH_KEYS) and all("\n" not in w for w in warnings)
    assert "config: [graph] associate_m is now [graph.landmarks] associate_m" in warnings
    assert "config: [graph] registration_tolerance_m is now [graph.registration] inlier_threshold_m" in warnings
    for old, (table, key) in LEGACY_GRAPH_KEYS.items():
        assert sum(w == f"config: [graph] {old} is now [graph.{table}] {key}" for w in warnings) == 1, old


def _other_key(part: object, key: str) -> object:
    """Another value for `part`'s field `key`, of its type (another of a Literal's choices) and within its bounds."""
    value = getattr(part, key)
    choices = typing.get_args(typing.get_type_hints(type(part))[key])
    if typing.get_origin(typing.get_type_hints(type(part))[key]) is typing.Literal:
        return next(c for c in choices if c != value)
    return 32 if key == "num_disparities" else _other(value)


def test_every_parameter_of_the_one_shot_registration_is_a_key_and_takes_effect() -> None:
    """[localize] is `RobustParams` with `method`: each of its fields a key, each nested parameter set (`verify`)
    a table; each key, set to another value, changes that one value of `robust_params()`."""
    from macroloc.graph.params import RobustParams
    from macroloc.service.config import LocalizeConfig

    section = pydantic.TypeAdapter(LocalizeConfig)
    assert {f.name for f in dataclasses.fields(LocalizeConfig)} - {"method"} == \
        {f.name for f in dataclasses.fields(RobustParams)}
    default = RobustParams()
    assert LocalizeConfig().robust_params() == default
    tables = [f.name for f in dataclasses.fields(RobustParams) if dataclasses.is_dataclass(getattr(default, f.name))]
    assert "verify" in tables
    for key in (f.name for f in dataclasses.fields(RobustParams) if f.name not in tables):
        value = _other_key(default, key)
        got = section.validate_python({key: value}).robust_params()
        assert got == dataclasses.replace(default, **{key: value}), key
    for table in tables:
        part = getattr(default, table)
        for key in (f.name for f in dataclasses.fields(part)):
            value = _other_key(part, key)
            got = section.validate_python({table: {key: value}}).robust_params()
            assert got == dataclasses.replace(default, **{table: dataclasses.replace(part, **{key: value})}), key


def test_every_parameter_of_the_perception_chain_is_a_key_and_takes_effect() -> None:
    """Each `PerceptionParams` part is its [perception.<part>] table; each of its keys, set to another value,
    changes that one value of `to_params()`; no key set: the chain's own defaults."""
    from macroloc.perception.params import PerceptionParams
    from macroloc.service.config import PerceptionConfig

    default = PerceptionParams()
    assert PerceptionConfig().to_params() == default
    for part in dataclasses.fields(PerceptionParams):
        assert type(getattr(PerceptionConfig(), part.name)) is type(getattr(default, part.name)), part.name
        for key in (f.name for f in dataclasses.fields(getattr(default, part.name))):
            other = _other_key(getattr(default, part.name), key)
            got = PerceptionConfig.model_validate({part.name: {key: other}}).to_params()
            want = dataclasses.replace(default, **{part.name: dataclasses.replace(getattr(default, part.name),
                                                                                 **{key: other})})
            assert got == want, f"[perception.{part.name}] {key}"


def test_one_name_for_the_registration_tolerance() -> None:
    """The one-shot localize's and the pose graph's registration gate are one idea, `inlier_threshold_m`,
    each with its own default; the pose graph's old name still loads."""
    from macroloc.graph.robust import RobustParams
    from macroloc.service.config import LocalizeConfig

    cfg = MacrolocConfig()
    assert cfg.localize.inlier_threshold_m == RobustParams().inlier_threshold_m == 0.30
    assert cfg.graph.registration.inlier_threshold_m == LocalizerParams().registration.inlier_threshold_m == 0.6
    assert LocalizeConfig(inlier_threshold_m=0.25).robust_params() == RobustParams(inlier_threshold_m=0.25)
    old = GraphConfig.model_validate({"registration_tolerance_m": 0.5})
    assert settings_from_config(old).localizer.registration.inlier_threshold_m == 0.5


@pytest.mark.parametrize("text, where", [
    ("[graph.judge]\nsurface_margn = 0.2\n", "graph.judge.surface_margn"),
    ("[graph.keyframes]\nkeyframe_interval_s = 0.5\n", "graph.keyframes.keyframe_interval_s"),
    ("[graph]\nassociate = 0.5\n", "graph.associate"),
    ("[graph.bogus]\nx = 1\n", "graph.bogus"),
])
def test_an_unknown_key_is_refused_in_one_line(tmp_path: Path, text: str, where: str) -> None:
    path = tmp_path / "config.toml"
    path.write_text(text)
    with pytest.raises(UserInputError) as info:
        load_config(path)
    assert str(info.value) == f"config: {where}: Extra inputs are not permitted"


def test_the_environment_overrides_a_nested_key(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """MACROLOC_GRAPH__<TABLE>__<KEY> over the file's key; the file's other keys of the table stay; a flat
    variable from before the tables still works."""
    path = tmp_path / "config.toml"
    path.write_text("[graph.judge]\nsurface_margin = 0.25\nsurface_turn_deg = 12.0\n")
    monkeypatch.setenv("MACROLOC_GRAPH__JUDGE__SURFACE_MARGIN", "0.2")
    monkeypatch.setenv("MACROLOC_GRAPH__KEYFRAMES__WHILE_EXPLORING", "true")
    monkeypatch.setenv("MACROLOC_GRAPH__ASSOCIATE_M", "0.45")
    s = settings_from_config(load_config(path).graph)
    assert (s.localizer.judge.surface_margin, s.localizer.judge.surface_turn_deg) == (0.2, 12.0)
    assert s.rule.while_exploring and s.localizer.landmarks.associate_m == 0.45


def test_a_flags_override_of_a_table_keeps_the_files_other_keys(tmp_path: Path) -> None:
    path = tmp_path / "config.toml"
    path.write_text("[graph.judge]\nsurface_margin = 0.25\nsurface_turn_deg = 12.0\n")
    cfg = load_config(path, graph={"judge": {"surface_margin": 0.2}, "storey_hint": "Level 1"})
    assert (cfg.graph.judge.surface_margin, cfg.graph.judge.surface_turn_deg) == (0.2, 12.0)
    assert cfg.graph.storey_hint == "Level 1"


def test_dump_config_prints_the_tables_and_reads_back(tmp_path: Path) -> None:
    from macroloc.cli.main import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["dump-config", "--toml"]) == 0
    text = out.getvalue()
    for table in TABLES:
        assert f"\n[graph.{table}]\n" in text
    assert "\n[graph.judge]\nsurface_min_points = 200\nsurface_min_support = 0.9\nsurface_margin = 0.3\n" in text
    path = tmp_path / "dumped.toml"
    path.write_text(text)
    assert load_config(path).graph == GraphConfig()


def test_a_window_too_short_for_the_surface_check_is_refused(tmp_path: Path) -> None:
    """The iSAM2 window must hold the keyframes the surface check reads back (0 keeps them all)."""
    path = tmp_path / "c.toml"
    path.write_text("[graph.isam]\nwindow_keyframes = 30\n")
    with pytest.raises(UserInputError, match="window_keyframes must be 0"):
        load_config(path)
    path.write_text("[graph.isam]\nwindow_keyframes = 0\n")
    assert settings_from_config(load_config(path).graph).isam.window_keyframes == 0


def test_a_key_is_declared_once_as_its_components_field(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A parameter is one line, `name: type = param(default, description, bounds)` in its component's dataclass:
    as a table of a config section, that line alone gives the key its default, check and description (the schema
    and docs/configuration.md read them), a file's and the environment's value, and its place in dump-config."""
    from pydantic import Field

    from macroloc.common.parameters import Parameters, param
    from macroloc.service.config import _Section

    @dataclasses.dataclass(frozen=True)
    class ExampleParams(Parameters):
        speed_mps: float = param(2.0, "an example key, m/s", gt=0, le=5)

    class Section(_Section):
        example: ExampleParams = Field(default_factory=ExampleParams, description="[x.example]: an example table")

    class Settings(pydantic_settings.BaseSettings):
        model_config = pydantic_settings.SettingsConfigDict(env_prefix="EXAMPLE_", env_nested_delimiter="__")
        x: Section = Field(default_factory=Section)

    schema = Settings.model_json_schema()["$defs"]["ExampleParams"]["properties"]["speed_mps"]
    assert schema == {"default": 2.0, "description": "an example key, m/s", "exclusiveMinimum": 0, "maximum": 5,
                      "title": "Speed Mps", "type": "number"}
    path = tmp_path / "example.toml"
    path.write_text("[x.example]\nspeed_mps = 3.5\n")
    assert Settings(**tomllib.loads(path.read_text())).x.example == ExampleParams(speed_mps=3.5)
    monkeypatch.setenv("EXAMPLE_X__EXAMPLE__SPEED_MPS", "4.0")
    assert Settings().x.example.speed_mps == 4.0 and Settings().model_dump() == {"x": {"example": {"speed_mps": 4.0}}}
    for bad in ({"speed_mps": 0.0}, {"speed_mps": 6.0}, {"speed": 1.0}):
        with pytest.raises(pydantic.ValidationError):
            Section.model_validate({"example": bad})
