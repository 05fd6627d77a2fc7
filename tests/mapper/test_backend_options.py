"""Backend options are typed: each reconstructor, segmenter and embedder has a pydantic options model
registered with it by name, the mapper config validates the chosen backend's options at load, and
``argus mapper --describe`` lists every backend's options."""

from __future__ import annotations

import subprocess
import sys
from importlib.metadata import EntryPoint
from pathlib import Path
from typing import Any

import pytest
from pydantic import BaseModel, ConfigDict, Field

from deploy.up import load_launch
from mapper.cli import describe_all
from mapper.config import GeometryConfig, MapperConfig, MapperCoreConfig, PerceptionConfig
from mapper.core import MapperCore
from mapper.geometry.registry import RECONSTRUCTORS, make_reconstructor
from mapper.perception.registry import EMBEDDERS, SEGMENTERS
from protocol.plugins import FreeOptions
from protocol.tomlconfig import ConfigError, load_config
from tests.support.procs import REPO

ROOT = REPO
REGISTRIES = {
    "geometry.options": RECONSTRUCTORS, "perception.segmenter_options": SEGMENTERS,
    "perception.embedder_options": EMBEDDERS,
}


def load(*overrides: str, path: Path | None = None) -> MapperConfig:
    return load_config(MapperConfig, path, None, list(overrides))


class TestValidatedAtLoad:
    def test_an_option_name_typo_names_the_backend_the_field_and_the_near_miss(self) -> None:
        with pytest.raises(ConfigError) as e:
            load("geometry.options.outptu_width=160")
        msg = str(e.value)
        assert "geometry.options" in msg and "reconstructor 'mvs'" in msg
        assert "'outptu_width'" in msg and "did you mean 'output_width'" in msg

    def test_a_wrong_type_names_the_backend_and_the_field(self) -> None:
        with pytest.raises(ConfigError, match=r"reconstructor 'oracle': option 'width': Input should be a valid"):
            load("geometry.backend=oracle", "geometry.options.width=wide")

    def test_segmenter_and_embedder_options_are_checked_against_their_own_backend(self, tmp_path: Path) -> None:
        toml = tmp_path / "m.toml"
        toml.write_text('perception = { segmenter = "detector", segmenter_options = { score_treshold = 0.4 } }\n')
        with pytest.raises(ConfigError, match=r"segmenter 'detector': no option 'score_treshold' \(did you mean "
                                              r"'score_threshold'"):
            load(path=toml)
        # an option of another backend is not one of this backend's
        with pytest.raises(ConfigError, match=r"embedder 'classical': no option 'vocabulary'"):
            load("perception.embedder_options.vocabulary=x.txt")

    def test_an_unknown_backend_is_an_error_at_load_listing_the_known_ones(self) -> None:
        with pytest.raises(ConfigError, match=r"geometry.backend: .*unknown reconstructor 'mvz'.*'mvs'"):
            load("geometry.backend=mvz")
        with pytest.raises(ConfigError, match=r"perception.segmenter: .*unknown segmenter 'nope'"):
            load("perception.segmenter=nope")

    def test_options_must_be_a_table(self) -> None:
        with pytest.raises(ConfigError, match="options of reconstructor 'mvs' must be a table"):
            load("geometry.options=3")

    def test_options_are_the_backends_model_with_its_defaults(self) -> None:
        cfg = load("geometry.backend=oracle", "geometry.options.width=48", "perception.segmenter=sim")
        assert type(cfg.geometry.options).__name__ == "OracleConfig"
        assert cfg.geometry.options.model_dump() == {"width": 48}
        assert type(cfg.perception.segmenter_options).__name__ == "SimSegmenterConfig"
        assert type(MapperConfig().geometry.options).__name__ == "MvsConfig"

    def test_a_dumped_config_loads_back_to_the_same_config(self) -> None:
        cfg = load("geometry.backend=oracle", "geometry.options.width=48",
                   "perception.segmenter_options.work_width=80")
        again = MapperConfig.model_validate(cfg.model_dump(mode="json"))
        assert again == cfg and again.geometry.options == cfg.geometry.options


def test_validated_options_reach_the_built_backends() -> None:
    core = MapperCore(MapperCoreConfig(
        geometry=GeometryConfig(backend="oracle", options={"width": 48}),
        perception=PerceptionConfig(segmenter_options={"work_width": 80}, embedder_options={"hue_bins": 6}),
    ))
    assert core.reconstructor.config.width == 48  # type: ignore[attr-defined]
    assert core.segmenter.config.work_width == 80  # type: ignore[attr-defined]
    assert core.embedder.config.hue_bins == 6  # type: ignore[attr-defined]


def test_make_reconstructor_checks_keyword_options_the_same_way() -> None:
    assert make_reconstructor("oracle", width=8).config.width == 8  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match=r"reconstructor 'oracle': no option 'widht' \(did you mean 'width'"):
        make_reconstructor("oracle", widht=8)


def test_every_shipped_launch_file_has_valid_mapper_backend_options() -> None:
    checked = 0
    for path in sorted((ROOT / "deploy" / "launch").glob("*.toml")):
        for proc in load_launch(path).process:
            if proc.command == "mapper" and proc.settings is not None:
                GeometryConfig.model_validate(proc.settings.get("geometry", {}))
                PerceptionConfig.model_validate(proc.settings.get("perception", {}))
                checked += 1
    assert checked >= 4


def test_describe_lists_every_option_of_every_builtin_backend() -> None:
    text = describe_all()
    for path, registry in REGISTRIES.items():
        for name in registry.builtins:
            model = registry.options_model(name)
            assert f"= {name!r}: options {path}.* ({model.__name__})" in text
            for field in model.model_fields:
                assert f"  {path}.{field} (" in text, (name, field)


@pytest.mark.integration
def test_options_models_do_not_import_optional_model_packages() -> None:
    """Loading a config (and every options model) must not import the optional model packages: only the
    chosen backend imports them, when it is built."""
    code = (
        "import sys\n"
        "from mapper.config import MapperConfig\n"
        "from mapper.geometry.registry import RECONSTRUCTORS\n"
        "from mapper.perception.registry import EMBEDDERS, SEGMENTERS\n"
        "MapperConfig()\n"
        "for r in (RECONSTRUCTORS, SEGMENTERS, EMBEDDERS):\n"
        "    [r.options_model(n) for n in r.builtins]\n"
        "heavy = {'mapanything', 'open_clip', 'segment_anything', 'depth_anything_3', 'uniception', 'torchvision'}\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in heavy))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120,
                         check=True)
    assert out.stdout.strip() == "[]"


# --- third-party backends through entry points --------------------------------------------------------------
class ToyOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")
    gain: float = Field(default=1.0, gt=0, description="toy gain")


class ToyReconstructor:
    Config = ToyOptions

    def __init__(self, **opts: Any) -> None:
        self.config = ToyOptions(**opts)


class LooseReconstructor:
    def __init__(self, **opts: Any) -> None:
        self.opts = opts


@pytest.fixture
def plugins(monkeypatch: pytest.MonkeyPatch) -> None:
    eps = [EntryPoint(name, f"tests.mapper.test_backend_options:{cls}", "argus.reconstructors")
           for name, cls in (("toy", "ToyReconstructor"), ("loose", "LooseReconstructor"))]
    monkeypatch.setattr("protocol.plugins.entry_points",
                        lambda group: [ep for ep in eps if ep.group == group])


@pytest.mark.usefixtures("plugins")
def test_a_plugin_with_a_config_is_validated_and_described_like_a_builtin() -> None:
    cfg = load("geometry.backend=toy", "geometry.options.gain=2.5")
    assert isinstance(cfg.geometry.options, ToyOptions) and cfg.geometry.options.gain == 2.5
    assert make_reconstructor("toy", cfg.geometry.options).config.gain == 2.5  # type: ignore[attr-defined]
    with pytest.raises(ConfigError, match="reconstructor 'toy': option 'gain'"):
        load("geometry.backend=toy", "geometry.options.gain=-1")
    assert "  geometry.options.gain (float, default 1.0): toy gain" in describe_all()


@pytest.mark.usefixtures("plugins")
def test_a_plugin_without_a_config_gets_its_options_unchecked() -> None:
    cfg = load("geometry.backend=loose", "geometry.options.anything=3")
    assert isinstance(cfg.geometry.options, FreeOptions)
    rec = make_reconstructor("loose", cfg.geometry.options)
    assert rec.opts == {"anything": 3}  # type: ignore[attr-defined]
