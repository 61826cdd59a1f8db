"""Seeded random streams of a synthetic sequence.

Every draw comes from a generator derived from ``options.seed`` with a
:class:`numpy.random.SeedSequence` spawn key whose first element names the stream (plan,
per-texture-tile, per-frame), so a result does not depend on the order in which frames or
textures are computed.
"""

from __future__ import annotations

import numpy as np

# Randomness streams (first element of the SeedSequence spawn key). A composite's objects and
# motion come from their own stream: the same seed does not repeat jsr synth's own scenes.
STREAM_PLAN, STREAM_TEXTURE, STREAM_FRAME, STREAM_COMPOSITE = 0, 1, 2, 3


def seeded_rng(seed: int, *key: int) -> np.random.Generator:
    """The generator of ``seed`` for spawn key ``key`` (its first element a ``STREAM_*``)."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=tuple(int(k) for k in key)))
