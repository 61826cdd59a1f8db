"""VLAD vocabulary, encoding and segment similarity search."""

from __future__ import annotations

import numpy as np
import pytest

from jsr.pipeline.vlad import SegmentIndex, VladVocabulary, kmeans


def _clusters(rng: np.random.Generator, centres: np.ndarray, per_cluster: int, noise: float) -> tuple[np.ndarray, np.ndarray]:
    labels = np.repeat(np.arange(len(centres)), per_cluster)
    data = centres[labels] + rng.normal(scale=noise, size=(len(labels), centres.shape[1]))
    return data.astype(np.float32), labels


def _random_centres(rng: np.random.Generator, k: int) -> np.ndarray:
    return rng.uniform(0.0, 100.0, size=(k, 128))


def test_kmeans_recovers_well_separated_clusters():
    rng = np.random.default_rng(0)
    truth = _random_centres(rng, 6)
    data, labels = _clusters(rng, truth, 50, noise=1.0)
    centres, found = kmeans(data, 6, np.random.default_rng(1))
    # Every true cluster maps to exactly one found cluster and vice versa.
    pairs = {(int(a), int(b)) for a, b in zip(labels, found)}
    assert len(pairs) == 6
    assert len({a for a, _ in pairs}) == 6 and len({b for _, b in pairs}) == 6
    # Centres land on the true centres.
    distance = np.linalg.norm(truth[:, None, :] - centres[None, :, :], axis=2)
    # The mean of 50 samples with noise 1.0 lies about 1.0 * sqrt(128 / 50) = 1.6 away.
    assert np.all(distance.min(axis=1) < 2.5)


def test_train_is_deterministic_for_a_seed_and_recovers_centres():
    rng = np.random.default_rng(2)
    truth = _random_centres(rng, 8)
    data, _ = _clusters(rng, truth, 40, noise=0.5)
    a = VladVocabulary.train(data, 8, np.random.default_rng(7))
    b = VladVocabulary.train(data, 8, np.random.default_rng(7))
    assert a.size == 8 and a.dimension == 8 * 128
    assert a.centres.dtype == np.float32
    np.testing.assert_array_equal(a.centres, b.centres)
    distance = np.linalg.norm(truth[:, None, :] - a.centres[None, :, :].astype(np.float64), axis=2)
    # The mean of 40 samples with noise 0.5 lies about 0.5 * sqrt(128 / 40) = 0.9 away.
    assert np.all(distance.min(axis=1) < 1.5)


def test_train_with_few_distinct_descriptors_shrinks_vocabulary():
    data = np.repeat(np.eye(128, dtype=np.float32)[:3], 2, axis=0)
    vocabulary = VladVocabulary.train(data, 16, np.random.default_rng(0))
    assert vocabulary.size == 3
    with pytest.raises(ValueError):
        VladVocabulary.train(np.zeros((0, 128), np.float32), 4, np.random.default_rng(0))


@pytest.mark.parametrize("normalization", ["power", "intra"])
def test_encoding_is_normalised_deterministic_and_zero_for_empty(normalization):
    rng = np.random.default_rng(3)
    data, _ = _clusters(rng, _random_centres(rng, 4), 30, noise=2.0)
    vocabulary = VladVocabulary.train(data, 4, np.random.default_rng(0), normalization=normalization)
    vlad = vocabulary.encode(data[:25])
    assert vlad.shape == (4 * 128,) and vlad.dtype == np.float32
    assert np.linalg.norm(vlad) == pytest.approx(1.0, abs=1e-5)
    np.testing.assert_array_equal(vlad, vocabulary.encode(data[:25]))
    empty = vocabulary.encode(np.zeros((0, 128), np.float32))
    assert empty.shape == (4 * 128,) and not empty.any()
    if normalization == "intra":
        blocks = vlad.reshape(4, 128)
        norms = np.linalg.norm(blocks, axis=1)
        used = norms > 0
        np.testing.assert_allclose(norms[used], 1.0 / np.sqrt(used.sum()), rtol=1e-5)


def test_encode_matches_a_direct_residual_sum():
    rng = np.random.default_rng(4)
    centres = rng.normal(size=(3, 128)).astype(np.float32)
    vocabulary = VladVocabulary(centres, normalization="power")
    data = (centres[[0, 0, 2, 2, 2]] + rng.normal(scale=0.05, size=(5, 128))).astype(np.float32)
    expected = np.zeros((3, 128))
    for row in data:
        word = np.argmin(np.linalg.norm(centres - row, axis=1))
        expected[word] += row - centres[word]
    expected = np.sign(expected) * np.sqrt(np.abs(expected))
    expected = expected.ravel() / np.linalg.norm(expected)
    np.testing.assert_allclose(vocabulary.encode(data), expected, atol=1e-5)
    assert not vocabulary.encode(data).reshape(3, 128)[1].any()  # word 1 got nothing


def test_encode_groups_equals_encode_per_group():
    rng = np.random.default_rng(5)
    data, _ = _clusters(rng, _random_centres(rng, 5), 20, noise=3.0)
    vocabulary = VladVocabulary.train(data, 5, np.random.default_rng(0))
    groups = [np.arange(0, 30), np.array([], dtype=np.int64), np.arange(50, 100, 3)]
    batch = vocabulary.encode_groups(data, groups)
    assert batch.shape == (3, 5 * 128)
    for row, group in zip(batch, groups):
        np.testing.assert_allclose(row, vocabulary.encode(data[group]), atol=1e-6)


def test_segment_vlad_is_most_similar_to_a_noisy_copy_of_itself():
    rng = np.random.default_rng(6)
    # A "scene" of 16 visual patterns; each segment draws its own mixture of them.
    patterns = rng.uniform(0.0, 50.0, size=(16, 128))
    training, _ = _clusters(rng, patterns, 30, noise=4.0)
    vocabulary = VladVocabulary.train(training, 16, np.random.default_rng(0))
    segments = []
    for _ in range(8):
        chosen = rng.choice(16, size=40)
        segments.append(patterns[chosen] + rng.normal(scale=4.0, size=(40, 128)))
    index = SegmentIndex()
    for key, descriptors in enumerate(segments):
        index.add(1, ("kf0", key), vocabulary.encode(descriptors.astype(np.float32)))
    assert len(index) == 8
    for key, descriptors in enumerate(segments):
        noisy = descriptors + rng.normal(scale=2.0, size=descriptors.shape)
        results = index.query(vocabulary.encode(noisy.astype(np.float32)), top_k=3)
        assert len(results) == 3
        assert results[0][0] == ("kf0", key)
        similarities = [s for _, s in results]
        assert similarities == sorted(similarities, reverse=True)
        assert results[0][1] > results[1][1]


def test_segment_index_ties_filters_and_replacement():
    index = SegmentIndex()
    a = np.zeros(256, np.float32)
    a[0] = 1.0
    b = np.zeros(256, np.float32)
    b[1] = 1.0
    index.add(1, "x", a)
    index.add(2, "y", 3.0 * a)  # same direction: tie with "x", added later
    index.add(1, "z", b)
    assert index.query(a, top_k=2) == [("x", pytest.approx(1.0)), ("y", pytest.approx(1.0))]
    assert [k for k, _ in index.query(a, top_k=5, object_map_id=1)] == ["x", "z"]
    assert index.query(a, top_k=0) == []
    index.add(1, "x", b)  # replace
    assert len(index) == 3
    assert index.query(a, top_k=1)[0][0] == "y"
    index.remove_map(2)
    assert index.object_map_ids() == [1]
    assert all(s == pytest.approx(0.0) for _, s in index.query(a, top_k=2))
    with pytest.raises(ValueError):
        index.query(np.zeros(10), top_k=1)
