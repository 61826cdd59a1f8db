from pathlib import Path

import pytest
import yaml

from jsr.config import Config, config_to_yaml, load_config, parse_override
from jsr.errors import ConfigError

DEFAULT_YAML = Path(__file__).resolve().parents[1] / "configs" / "default.yaml"


def test_default_yaml_matches_dataclass_defaults():
    assert yaml.safe_load(DEFAULT_YAML.read_text()) == Config().to_dict()


def test_every_default_yaml_key_has_a_comment():
    for line in DEFAULT_YAML.read_text().splitlines():
        stripped = line.strip()
        if stripped and not stripped.startswith("#") and not stripped.endswith(":"):
            assert "#" in stripped, f"no comment on config line: {line!r}"


def test_paper_thresholds_are_the_defaults():
    config = Config()
    assert config.ransac.min_inlier_ratio == 0.4
    assert config.ransac.min_matches == 10
    assert config.noise.min_inlier_threshold == 0.01
    assert config.noise.inlier_sigmas == 3.0
    assert config.noise.sigma_z_coefficient == pytest.approx(1.425e-3)


def test_file_then_overrides(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("ransac:\n  min_matches: 20\nkeyframes:\n  translation: 0.2\n")
    config = load_config(path, ["ransac.min_matches=12", "planes.refine=false", "noise.inlier_sigmas=2"])
    assert config.ransac.min_matches == 12
    assert config.keyframes.translation == 0.2
    assert config.planes.refine is False
    assert config.noise.inlier_sigmas == 2.0 and isinstance(config.noise.inlier_sigmas, float)
    # untouched keys keep their defaults
    assert config.ransac.min_inlier_ratio == 0.4


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("ransac:\n  min_inlier_rati: 0.4\n", "ransac.min_inlier_rati"),
        ("ransacc:\n  min_matches: 3\n", "ransacc"),
        ("ransac:\n  min_matches: many\n", "ransac.min_matches"),
        ("ransac:\n  min_matches: 10.5\n", "ransac.min_matches"),
        ("planes:\n  refine: 1\n", "planes.refine"),
        ("ransac: 5\n", "ransac"),
        ("ransac:\n  min_inlier_ratio: 1.5\n", "ransac.min_inlier_ratio"),
        ("- a\n- b\n", "mapping"),
        ("ransac: [\n", "not valid YAML"),
        ("ransac:\n  min_matches: 3\n  seed: [1\n", "not valid YAML: line 4"),  # where, to find it
    ],
)
def test_bad_config_files_name_the_key(tmp_path, text, fragment):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as error:
        load_config(path)
    assert fragment in str(error.value)
    assert "\n" not in str(error.value)


def test_unknown_key_suggests_the_close_one():
    with pytest.raises(ConfigError, match="did you mean 'min_inlier_ratio'"):
        load_config(None, ["ransac.min_inlier_rati=0.3"])


def test_bad_overrides():
    with pytest.raises(ConfigError, match="section.key=value"):
        load_config(None, ["ransac.min_matches"])
    with pytest.raises(ConfigError, match="ransac.min_matches"):
        load_config(None, ["ransac.min_matches=abc"])
    with pytest.raises(ConfigError, match="min_depth"):
        load_config(None, ["input.min_depth=7", "input.max_depth=6"])
    with pytest.raises(ConfigError, match=r"is a section, not a value.*--set ransac\.min_inlier_ratio="):
        load_config(None, ["ransac=5"])


def test_floats_in_exponent_notation(tmp_path):
    """YAML 1.1 reads 1e-6 (no dot) as a string; a float key takes it as the number, from a
    file and from --set alike, and an int key does not."""
    assert load_config(None, ["detection.displaced_significance=1e-9"]).detection.displaced_significance == 1e-9
    path = tmp_path / "c.yaml"
    path.write_text("detection:\n  displaced_significance: 2E-7\n")
    assert load_config(path).detection.displaced_significance == 2e-7
    with pytest.raises(ConfigError, match="ransac.min_matches"):
        load_config(None, ["ransac.min_matches=1e1"])
    with pytest.raises(ConfigError, match="displaced_significance"):
        load_config(None, ["detection.displaced_significance=1e-x"])


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "nope.yaml")


def test_parse_override_values():
    assert parse_override("a.b=0.5") == ("a.b", 0.5)
    assert parse_override("a.b=true") == ("a.b", True)
    assert parse_override("a.b=text") == ("a.b", "text")


def test_resolved_config_round_trips(tmp_path):
    config = load_config(None, ["seed=7", "vlad.vocabulary_size=32"])
    path = tmp_path / "resolved.yaml"
    path.write_text(config_to_yaml(config))
    assert load_config(path) == config
