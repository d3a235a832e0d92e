"""wc.rotations: the numpy and torch maps agree, matrices are proper rotations, conversions round-trip."""

from __future__ import annotations

import numpy as np
import torch

from wc.rotations import (quat_conjugate, quat_from_matrix, quat_matrices, quat_matrices_torch, quat_multiply,
                          quat_rotate, quat_rotate_torch)


def _unit_quats(n: int, seed: int = 0) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_numpy_and_torch_agree() -> None:
    q, p = _unit_quats(16), np.random.default_rng(1).normal(size=(16, 3))
    np.testing.assert_allclose(quat_rotate_torch(torch.as_tensor(q), torch.as_tensor(p)).numpy(), quat_rotate(q, p),
                               atol=1e-12)
    np.testing.assert_allclose(quat_matrices_torch(torch.as_tensor(q)).numpy(), quat_matrices(q), atol=1e-12)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", quat_matrices(q), p), quat_rotate(q, p), atol=1e-12)


def test_matrices_are_rotations_and_round_trip() -> None:
    q = _unit_quats(32, seed=2)
    r = quat_matrices(q)
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)
    for qi, ri in zip(q, r):
        back = quat_from_matrix(ri)
        assert min(np.abs(back - qi).max(), np.abs(back + qi).max()) < 1e-9  # q and -q are one rotation


def test_product_and_conjugate() -> None:
    a, b = _unit_quats(8, seed=3), _unit_quats(8, seed=4)
    p = np.random.default_rng(5).normal(size=(8, 3))
    np.testing.assert_allclose(quat_rotate(quat_multiply(a, b), p), quat_rotate(a, quat_rotate(b, p)), atol=1e-12)
    identity = quat_multiply(a, quat_conjugate(a))
    np.testing.assert_allclose(identity, np.tile([0.0, 0.0, 0.0, 1.0], (8, 1)), atol=1e-12)
    assert quat_conjugate(a.astype(np.float32)).dtype == np.float32
