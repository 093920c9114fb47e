"""The reference frames a node keeps to warp into views: bounded, the most redundant evicted."""

from __future__ import annotations

import numpy as np
import pytest

from gsfix_online.core.se3 import make_T
from gsfix_online.repair.references import ReferenceStore, reference_from_arrays, warp_arrays

K = np.array([[20.0, 0, 7.5], [0, 20.0, 5.5], [0, 0, 1]])


def arrays(x: float) -> dict[str, np.ndarray]:
    return {"color": np.full((12, 16, 3), int(10 * x) % 255, np.uint8),
            "depth": np.full((12, 16), 2.0, np.float32), "K": K,
            "T_world_cam": make_T(np.eye(3), [x, 0.0, 0.0])}  # fmt: skip


def test_the_store_is_bounded_evicts_the_most_redundant_and_replaces_by_id():
    store = ReferenceStore(capacity=3)
    for i, x in enumerate((0.0, 1.0, 1.05, 3.0)):  # 1.0 and 1.05 nearly coincide
        store.add(i, reference_from_arrays(arrays(x)))
    assert len(store) == 3 and store.n_evicted == 1
    xs = sorted(float(r.T_world_cam[0, 3]) for r in store.refs)
    assert xs == [0.0, 1.05, 3.0]  # the older of the close pair went, the newest stays
    store.add(3, reference_from_arrays(arrays(5.0)))  # a resent id replaces, evicts nothing
    assert len(store) == 3 and store.n_evicted == 1
    assert store.refs[-1].T_world_cam[0, 3] == 5.0


def test_a_warp_comes_back_from_its_message_and_bad_arrays_are_named():
    assert (
        ReferenceStore().warp(K, np.eye(4), np.ones((12, 16)), np.ones((12, 16), bool), None)
        is None
    )  # fmt: skip  (empty: no warp)
    image, valid = warp_arrays({"color": np.ones((2, 2, 3)), "alpha": np.array([[1.0, 0.0]] * 2)})
    assert image.dtype == np.uint8 and valid.tolist() == [[True, False]] * 2
    assert warp_arrays(None) == (None, None)
    with pytest.raises(ValueError, match=r"needs arrays \['depth'\]"):
        reference_from_arrays({k: v for k, v in arrays(0.0).items() if k != "depth"})
    with pytest.raises(ValueError, match="capacity must be an int >= 1"):
        ReferenceStore(0)
