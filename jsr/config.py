"""Typed configuration: every threshold of the method, loaded from YAML with overrides.

The dataclasses below hold the defaults; ``configs/default.yaml`` repeats them with a
comment per key (a test keeps the two identical). A config is built with
:func:`load_config`, which starts from the defaults, applies a YAML file and then
``section.key=value`` overrides. An unknown key or a value of the wrong type is rejected
with a :class:`~jsr.errors.ConfigError` that names the key.
"""

from __future__ import annotations

import dataclasses
import difflib
import re
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from jsr.errors import ConfigError
from jsr.io.text import describe_yaml_error, read_user_text


@dataclass
class InputConfig:
    """How frames are read."""

    max_time_difference: float = 0.02
    min_depth: float = 0.1
    max_depth: float = 6.0


@dataclass
class NoiseConfig:
    """Depth noise model and the inlier threshold derived from it."""

    sigma_z_coefficient: float = 1.425e-3
    inlier_sigmas: float = 3.0
    min_inlier_threshold: float = 0.01
    pixel_sigma: float = 1.5


@dataclass
class FeaturesConfig:
    """SIFT point measurements."""

    max_keypoints: int = 1500
    contrast_threshold: float = 0.02
    edge_threshold: float = 10.0
    half_resolution: bool = True
    object_detail: bool = True
    object_detail_margin: float = 0.5
    depth_window: int = 2
    depth_spread_sigmas: float = 6.0
    min_depth_spread: float = 0.02
    slanted_max_incidence: float = 0.0
    undistort: bool = True


@dataclass
class PlanesConfig:
    """Fast plane extraction on the organized point cloud (Feng, Taguchi and Kamat 2014)."""

    enabled: bool = True
    block_size: int = 10
    max_block_missing: float = 0.1
    max_block_rmse_sigmas: float = 2.0
    merge_angle_degrees: float = 8.0
    merge_rmse_sigmas: float = 3.0
    angle_noise_sigmas: float = 3.0
    min_plane_pixels: int = 2000
    depth_jump_sigmas: float = 6.0
    min_depth_jump: float = 0.02
    refine: bool = True
    refine_distance_sigmas: float = 3.0


@dataclass
class SegmentsConfig:
    """Depth segmentation of the pixels outside planes."""

    discontinuity_sigmas: float = 4.0
    min_discontinuity: float = 0.02
    min_segment_pixels: int = 400
    concave_angle_degrees: float = 30.0


@dataclass
class MatchingConfig:
    """Descriptor and plane matching."""

    ratio_test: float = 0.8
    recent_keyframes: int = 5
    plane_angle_degrees: float = 10.0
    plane_distance: float = 0.05
    guided_radius_px: float = 15.0
    max_descriptor_distance: float = 0.7
    bridge_with_previous_frame: bool = True


@dataclass
class RansacConfig:
    """Mixed point/plane RANSAC registration."""

    min_inlier_ratio: float = 0.4
    min_matches: int = 10
    min_inliers: int = 8
    max_iterations: int = 1000
    confidence: float = 0.999
    plane_inlier_angle_degrees: float = 5.0
    plane_inlier_distance: float = 0.05
    batch_size: int = 64
    sample_2d_below: int = 20
    refine_rounds: int = 3
    refinement: str = "image"
    depth_fallback: float = 3.0


@dataclass
class KeyframesConfig:
    """When a registered frame becomes a new keyframe of a map."""

    translation: float = 0.1
    rotation_degrees: float = 10.0
    tracked_share: float = 0.7
    weak_inliers: int = 100
    static_min_inliers: int = 50


@dataclass
class DetectionConfig:
    """Moving-object detection from segment outlier ratios."""

    segment_outlier_ratio: float = 0.6
    min_segment_features: int = 5
    significance: float = 0.01
    require_rigid_motion: bool = True
    free_space_veto_motion: float = 0.06
    in_place_turn_degrees: float = 10.0
    in_place_turn_memory_frames: int = 3
    min_motion: float = 0.03
    min_motion_degrees: float = 3.0
    displaced_share: float = 0.8
    displaced_significance: float = 1e-6
    merge_gap_pixels: int = 2
    min_object_points: int = 15
    confirm_frames: int = 3
    confirm_window: int = 6
    confirm_significance: float = 0.001
    dynamic_margin_px: int = 8


@dataclass
class ObjectsConfig:
    """Object maps: multi-group registration, classification and static-map hygiene."""

    enabled: bool = True
    segment_registration: str = "always"
    segment_completion: bool = True
    grow_segments: bool = True
    grow_violation_share: float = 0.3
    grow_unmatched: bool = True
    grow_inside_extent: bool = True
    split_mixed_segments: bool = True
    extent_margin: float = 0.03
    extent_share: float = 0.5
    extent_from_surface: bool = True
    extent_unseen_only: bool = True
    retire_object_matches: bool = True
    hold_back_suspects: bool = True
    hold_back_beside_moved: bool = True
    retire_after_vacated: int = 3
    vacated_cluster_size: int = 5
    vacated_cluster_radius: float = 0.15
    vacated_window_px: int = 10
    grow_keyframe_ratio: float = 1.0
    resting_max_extra_cost: float = 16.8
    reidentify: bool = True
    shape_reidentify: bool = True
    shape_attempts: int = 2
    shape_alignments_per_frame: int = 2
    shape_voxel: float = 0.01
    shape_radius_px: float = 40.0
    shape_min_fitness: float = 0.5
    shape_max_seen_through: float = 0.05
    shape_min_constraint: float = 0.015
    shape_min_texture_ratio: float = 0.5
    merge_maps: bool = True
    merge_min_shared_inliers: int = 5
    free_space_detection: bool = True
    free_space_margin: float = 0.1
    free_space_sigmas: float = 10.0
    free_space_min_pixels: int = 400
    free_space_share: float = 0.6
    free_space_min_segment_pixels: int = 1000
    free_space_registered: bool = True
    dormant_after_frames: int = 15
    reidentify_maps: int = 3


@dataclass
class DenseConfig:
    """The dense geometric term of static tracking (frame depth against keyframe depth)."""

    enabled: bool = False
    carry_below_inliers: int = 0
    refine: bool = False
    stride: int = 8
    keyframes: int = 3
    max_distance: float = 0.15
    gate_sigmas: float = 5.0
    iterations: int = 5
    min_overlap: float = 0.5
    min_normal_spread: float = 0.01
    trust_within: float = 0.02
    trust_keyframes: int = 5


@dataclass
class LoopClosureConfig:
    """Loop closure of the static map (place recognition, verification, pose graph)."""

    enabled: bool = True
    min_keyframe_gap: int = 10
    candidates: int = 3
    min_inliers: int = 50


@dataclass
class VladConfig:
    """Segment appearance descriptors for segment-based registration."""

    vocabulary_size: int = 64
    candidate_segments: int = 3
    max_pairs: int = 6
    min_segment_points: int = 8
    training_descriptors: int = 20000
    kmeans_iterations: int = 30
    normalization: str = "power"


@dataclass
class BundleAdjustmentConfig:
    """Per-map bundle adjustment."""

    enabled: bool = True
    every_keyframes: int = 5
    window_keyframes: int = 10
    max_iterations: int = 50
    huber_sigmas: float = 2.0
    asynchronous: bool = True
    pixel_sigma: float = 1.0
    plane_normal_sigma: float = 0.01
    plane_offset_sigma: float = 0.01
    min_shared_landmarks: int = 3
    link_max_spread: float = 3.0
    estimate_noise: bool = True
    final_global: bool = True


@dataclass
class OutputConfig:
    """What a reconstruction writes besides trajectories and counts."""

    mesh_voxel_size: float = 0.01


@dataclass
class Config:
    """The whole configuration of a run."""

    seed: int = 0
    input: InputConfig = field(default_factory=InputConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    features: FeaturesConfig = field(default_factory=FeaturesConfig)
    planes: PlanesConfig = field(default_factory=PlanesConfig)
    segments: SegmentsConfig = field(default_factory=SegmentsConfig)
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    ransac: RansacConfig = field(default_factory=RansacConfig)
    keyframes: KeyframesConfig = field(default_factory=KeyframesConfig)
    detection: DetectionConfig = field(default_factory=DetectionConfig)
    objects: ObjectsConfig = field(default_factory=ObjectsConfig)
    vlad: VladConfig = field(default_factory=VladConfig)
    bundle_adjustment: BundleAdjustmentConfig = field(default_factory=BundleAdjustmentConfig)
    dense: DenseConfig = field(default_factory=DenseConfig)
    loop_closure: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict, in declaration order (for YAML/JSON output)."""
        return dataclasses.asdict(self)


# Range checks that a type alone cannot express: key -> (test, what it must be).
_CONSTRAINTS: dict[str, tuple[typing.Callable[[Any], bool], str]] = {
    "seed": (lambda v: 0 <= v < 2**63, "a whole number >= 0"),
    "input.max_time_difference": (lambda v: v > 0, "positive"),
    "input.min_depth": (lambda v: v >= 0, "at least 0"),
    "input.max_depth": (lambda v: v > 0, "positive"),
    "noise.sigma_z_coefficient": (lambda v: v >= 0, "at least 0"),
    "noise.inlier_sigmas": (lambda v: v > 0, "positive"),
    "noise.min_inlier_threshold": (lambda v: v > 0, "positive"),
    "noise.pixel_sigma": (lambda v: v > 0, "positive"),
    "features.max_keypoints": (lambda v: v >= 0, "at least 0 (0 keeps all)"),
    "features.depth_window": (lambda v: v >= 0, "at least 0"),
    "features.depth_spread_sigmas": (lambda v: v > 0, "positive"),
    "features.min_depth_spread": (lambda v: v > 0, "positive"),
    "planes.block_size": (lambda v: v >= 3, "at least 3"),
    "planes.max_block_missing": (lambda v: 0 <= v < 1, "in [0, 1)"),
    "planes.max_block_rmse_sigmas": (lambda v: v > 0, "positive"),
    "planes.merge_angle_degrees": (lambda v: 0 < v < 90, "in (0, 90)"),
    "planes.merge_rmse_sigmas": (lambda v: v > 0, "positive"),
    "planes.angle_noise_sigmas": (lambda v: v >= 0, "at least 0"),
    "planes.min_plane_pixels": (lambda v: v >= 1, "at least 1"),
    "planes.depth_jump_sigmas": (lambda v: v > 0, "positive"),
    "planes.min_depth_jump": (lambda v: v > 0, "positive"),
    "planes.refine_distance_sigmas": (lambda v: v > 0, "positive"),
    "segments.discontinuity_sigmas": (lambda v: v > 0, "positive"),
    "segments.min_discontinuity": (lambda v: v > 0, "positive"),
    "segments.min_segment_pixels": (lambda v: v >= 1, "at least 1"),
    "matching.ratio_test": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "matching.recent_keyframes": (lambda v: v >= 1, "at least 1"),
    "matching.guided_radius_px": (lambda v: v > 0, "positive"),
    "matching.max_descriptor_distance": (lambda v: 0 < v <= 2, "in (0, 2]"),
    "ransac.min_inlier_ratio": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "ransac.min_matches": (lambda v: v >= 3, "at least 3"),
    "ransac.min_inliers": (lambda v: v >= 3, "at least 3"),
    "ransac.max_iterations": (lambda v: v >= 1, "at least 1"),
    "ransac.confidence": (lambda v: 0 < v < 1, "in (0, 1)"),
    "ransac.plane_inlier_angle_degrees": (lambda v: 0 < v < 90, "in (0, 90)"),
    "ransac.plane_inlier_distance": (lambda v: v > 0, "positive"),
    "ransac.batch_size": (lambda v: v >= 1, "at least 1"),
    "ransac.sample_2d_below": (lambda v: v >= 3, "at least 3"),
    "ransac.refine_rounds": (lambda v: v >= 0, "at least 0 (0 disables refinement)"),
    "ransac.depth_fallback": (lambda v: v == 0 or v >= 1, "0 (off) or at least 1"),
    "keyframes.translation": (lambda v: v >= 0, "at least 0"),
    "keyframes.rotation_degrees": (lambda v: v >= 0, "at least 0"),
    "keyframes.tracked_share": (lambda v: 0 <= v < 1, "in [0, 1) (0: off)"),
    "keyframes.weak_inliers": (lambda v: v >= 0, "at least 0"),
    "keyframes.static_min_inliers": (lambda v: v >= 0, "at least 0"),
    "detection.segment_outlier_ratio": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "detection.min_segment_features": (lambda v: v >= 1, "at least 1"),
    "detection.merge_gap_pixels": (lambda v: v >= 0, "at least 0"),
    "detection.min_motion": (lambda v: v >= 0, "at least 0"),
    "detection.min_motion_degrees": (lambda v: v >= 0, "at least 0"),
    "detection.significance": (lambda v: 0 < v <= 1, "in (0, 1] (1: no test)"),
    "detection.min_object_points": (lambda v: v >= 3, "at least 3"),
    "detection.confirm_frames": (lambda v: v >= 0, "at least 0 (0: a detected region is an object at once)"),
    "detection.confirm_window": (lambda v: v >= 1, "at least 1"),
    "detection.confirm_significance": (lambda v: 0 < v < 1, "in (0, 1)"),
    "detection.dynamic_margin_px": (lambda v: v >= 0, "at least 0"),
    "objects.dormant_after_frames": (lambda v: v >= 1, "at least 1"),
    "objects.reidentify_maps": (lambda v: v >= 1, "at least 1"),
    "objects.retire_after_vacated": (lambda v: v >= 0, "at least 0 (0: never)"),
    "objects.vacated_cluster_size": (lambda v: v >= 0, "at least 0 (0: no cluster needed)"),
    "objects.vacated_cluster_radius": (lambda v: v > 0, "positive"),
    "objects.grow_keyframe_ratio": (lambda v: v >= 0, "at least 0 (0: keyframes by view change only)"),
    "objects.vacated_window_px": (lambda v: v >= 0, "at least 0 (0: the projected pixel alone)"),
    "objects.free_space_margin": (lambda v: v > 0, "positive"),
    "objects.extent_margin": (lambda v: v >= 0, "at least 0"),
    "detection.in_place_turn_degrees": (lambda v: v >= 0, "at least 0 (0: the in-place test always vetoes)"),
    "detection.in_place_turn_memory_frames": (lambda v: v >= 0, "at least 0 (0: one frame alone confirms a turn)"),
    "objects.grow_violation_share": (lambda v: 0 <= v <= 1, "between 0 and 1 (0: off)"),
    "detection.free_space_veto_motion": (lambda v: v >= 0, "at least 0 (0: no veto)"),
    "segments.concave_angle_degrees": (lambda v: 0 <= v < 180, "in [0, 180) (0: no crease cuts)"),
    "objects.extent_share": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "objects.free_space_sigmas": (lambda v: v > 0, "positive"),
    "objects.shape_voxel": (lambda v: v > 0, "positive"),
    "features.object_detail_margin": (lambda v: v >= 0, "at least 0"),
    "features.slanted_max_incidence": (lambda v: 0 <= v < 90, "in [0, 90) degrees (0: off)"),
    "objects.shape_radius_px": (lambda v: v > 0, "positive"),
    "detection.displaced_share": (lambda v: 0 <= v <= 1, "in [0, 1] (0: off)"),
    "detection.displaced_significance": (lambda v: 0 < v < 1, "in (0, 1)"),
    "objects.shape_min_fitness": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "objects.shape_max_seen_through": (lambda v: 0 <= v <= 1, "in [0, 1]"),
    "objects.shape_min_constraint": (lambda v: v >= 0, "non-negative"),
    "objects.shape_min_texture_ratio": (lambda v: 0 <= v <= 1, "in [0, 1] (0: only fits that landmarks confirm)"),
    "objects.resting_max_extra_cost": (lambda v: v >= 0, "at least 0 (0: off)"),
    "objects.merge_min_shared_inliers": (lambda v: v >= 1, "at least 1"),
    "objects.free_space_min_pixels": (lambda v: v >= 1, "at least 1"),
    "objects.free_space_min_segment_pixels": (lambda v: v >= 1, "at least 1"),
    "objects.free_space_share": (lambda v: 0.5 <= v <= 1, "in [0.5, 1]"),
    "vlad.vocabulary_size": (lambda v: v >= 2, "at least 2"),
    "vlad.max_pairs": (lambda v: v >= 1, "at least 1"),
    "vlad.min_segment_points": (lambda v: v >= 3, "at least 3"),
    "vlad.training_descriptors": (lambda v: v >= 100, "at least 100"),
    "vlad.kmeans_iterations": (lambda v: v >= 1, "at least 1"),
    "vlad.candidate_segments": (lambda v: v >= 1, "at least 1"),
    "dense.carry_below_inliers": (lambda v: v >= 0, "at least 0 (0: only frames whose features fail)"),
    "dense.stride": (lambda v: v >= 1, "at least 1"),
    "dense.keyframes": (lambda v: v >= 1, "at least 1"),
    "dense.max_distance": (lambda v: v > 0, "positive"),
    "dense.gate_sigmas": (lambda v: v > 0, "positive"),
    "dense.iterations": (lambda v: v >= 1, "at least 1"),
    "dense.min_overlap": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "dense.min_normal_spread": (lambda v: 0 <= v <= 1 / 3, "in [0, 1/3]"),
    "dense.trust_within": (lambda v: v >= 0, "at least 0 (0: the depth is always trusted)"),
    "dense.trust_keyframes": (lambda v: v >= 1, "at least 1"),
    "loop_closure.min_keyframe_gap": (lambda v: v >= 1, "at least 1"),
    "loop_closure.candidates": (lambda v: v >= 1, "at least 1"),
    "loop_closure.min_inliers": (lambda v: v >= 3, "at least 3"),
    "objects.shape_attempts": (lambda v: v >= 1, "at least 1"),
    "objects.shape_alignments_per_frame": (lambda v: v >= 1, "at least 1"),
    "bundle_adjustment.every_keyframes": (lambda v: v >= 1, "at least 1"),
    "bundle_adjustment.window_keyframes": (lambda v: v >= 2, "at least 2"),
    "bundle_adjustment.max_iterations": (lambda v: v >= 1, "at least 1"),
    "bundle_adjustment.huber_sigmas": (lambda v: v > 0, "positive"),
    "bundle_adjustment.pixel_sigma": (lambda v: v > 0, "positive"),
    "bundle_adjustment.plane_normal_sigma": (lambda v: v > 0, "positive"),
    "bundle_adjustment.plane_offset_sigma": (lambda v: v > 0, "positive"),
    "bundle_adjustment.min_shared_landmarks": (lambda v: v >= 1, "at least 1"),
    "bundle_adjustment.link_max_spread": (lambda v: v >= 0, "at least 0 (0: shared landmarks link by their count)"),
    "output.mesh_voxel_size": (lambda v: v > 0, "positive"),
}


_CHOICES: dict[str, tuple[str, ...]] = {
    "ransac.refinement": ("image", "euclidean"),
    "objects.segment_registration": ("always", "fallback", "off"),
    "vlad.normalization": ("power", "intra"),
}


_EXPONENT_FLOAT = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")


def _type_name(expected: Any) -> str:
    return getattr(expected, "__name__", str(expected))


def _coerce(key: str, value: Any, expected: Any) -> Any:
    """Check ``value`` against the annotated type; ints are accepted where floats are expected."""
    if expected is bool:
        if isinstance(value, bool):
            return value
    elif expected is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif expected is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str) and _EXPONENT_FLOAT.fullmatch(value.strip()):
            return float(value)  # YAML 1.1 reads 1e-6 (no dot) as a string
    elif expected is str:
        if isinstance(value, str):
            return value
    else:  # pragma: no cover - guards future field types
        raise ConfigError(f"config key '{key}' has an unsupported type {expected!r}")
    raise ConfigError(f"config key '{key}' must be {_type_name(expected)}, got {value!r}")


def _unknown_key_error(key: str, known: list[str]) -> ConfigError:
    guess = difflib.get_close_matches(key.rsplit(".", 1)[-1], known, n=1)
    hint = f"; did you mean '{guess[0]}'?" if guess else f"; known keys: {', '.join(known)}"
    return ConfigError(f"unknown config key '{key}'{hint}")


def _apply_mapping(target: Any, values: dict, prefix: str) -> None:
    """Copy a nested mapping onto dataclass ``target`` in place, checking keys and types."""
    hints = typing.get_type_hints(type(target))
    known = [f.name for f in dataclasses.fields(target)]
    for name, value in values.items():
        key = f"{prefix}{name}"
        if name not in hints:
            raise _unknown_key_error(key, known)
        current = getattr(target, name)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                example = f"{key}.{dataclasses.fields(current)[0].name}"
                raise ConfigError(f"config key '{key}' is a section, not a value: give its keys (a mapping in a "
                                  f"config file; with --set, one key at a time: --set {example}=...)")
            _apply_mapping(current, value, f"{key}.")
            continue
        coerced = _coerce(key, value, hints[name])
        if key in _CHOICES and coerced not in _CHOICES[key]:
            raise ConfigError(f"config key '{key}' must be one of {', '.join(_CHOICES[key])}, got {value!r}")
        constraint = _CONSTRAINTS.get(key)
        if constraint is not None and not constraint[0](coerced):
            raise ConfigError(f"config key '{key}' must be {constraint[1]}, got {value!r}")
        setattr(target, name, coerced)


def parse_override(text: str) -> tuple[str, Any]:
    """Split ``section.key=value``; the value is parsed as YAML (``0.5``, ``true``, ``[1, 2]``)."""
    if "=" not in text:
        raise ConfigError(f"override '{text}' must look like section.key=value")
    key, raw_value = text.split("=", 1)
    key = key.strip()
    if not key:
        raise ConfigError(f"override '{text}' has no key before '='")
    try:
        value = yaml.safe_load(raw_value) if raw_value.strip() else ""
    except yaml.YAMLError:
        value = raw_value
    return key, value


def _nest(key: str, value: Any) -> dict:
    nested: Any = value
    for part in reversed(key.split(".")):
        nested = {part: nested}
    return nested


def load_config(path: Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """Defaults, then the YAML file at ``path`` (if any), then ``section.key=value`` overrides."""
    config = Config()
    if path is not None:
        path = Path(path)
        text = read_user_text(path, "config file", ConfigError)
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as error:
            raise ConfigError(f"config file {path} is not valid YAML: {describe_yaml_error(error)}") from None
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ConfigError(f"config file {path} must hold a mapping of sections")
        _apply_mapping(config, data, "")
    for override in overrides:
        key, value = parse_override(override)
        _apply_mapping(config, _nest(key, value), "")
    _check_relations(config)
    return config


def _check_relations(config: Config) -> None:
    """Keys whose valid values depend on another key (each key alone is checked on reading)."""
    if config.input.min_depth >= config.input.max_depth:
        raise ConfigError("config key 'input.min_depth' must be smaller than 'input.max_depth'")


def config_to_yaml(config: Config) -> str:
    """YAML text of a resolved config (what is written into every output folder)."""
    return yaml.safe_dump(config.to_dict(), sort_keys=False)
