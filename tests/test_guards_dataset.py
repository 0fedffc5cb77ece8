"""The demonstration dataset survives ``write_demos`` -> ``load_demos`` unchanged.

Guards the loader against reading one column as another (e.g. the reference as the output):
every array of the reloaded set must equal the generated one exactly, and the output must be
the plant's ``C x`` recomputed here from the stored states.
"""

from __future__ import annotations

import numpy as np

from generalist_control.data.demos import load_demos
from generalist_control.plants.catalog import load_plant
from generalist_control.plants.definition import MAX_ORDER

ARRAYS = ("x", "r", "u", "y", "tag", "order", "plant", "amplitude")


def test_reloaded_dataset_equals_the_generated_arrays_exactly(tiny_demos, tiny_data_dir):
    """``tiny_data_dir`` is ``tiny_demos`` written by ``write_demos`` (conftest.py)."""
    loaded, manifest = load_demos(tiny_data_dir)
    B, N = tiny_demos.r.shape
    assert manifest["n_trajectories"] == B and manifest["steps_per_trajectory"] == N
    for name in ARRAYS:
        want, got = getattr(tiny_demos, name), getattr(loaded, name)
        assert got.shape == want.shape, name
        np.testing.assert_array_equal(got, want, err_msg=f"DemoSet.{name} changed on reload")
    assert loaded.x.shape == (B, N, MAX_ORDER)
    assert loaded.dt == tiny_demos.dt == 0.05
    # the columns are not interchangeable: a step response differs from its reference
    assert not np.array_equal(loaded.y, loaded.r)
    assert not np.array_equal(loaded.u, loaded.r)
    # from rest: the output starts at zero while the reference is already at the step
    np.testing.assert_array_equal(loaded.y[:, 0], 0.0)
    np.testing.assert_array_equal(loaded.r, np.repeat(loaded.amplitude[:, None], N, axis=1))


def test_reloaded_output_is_c_times_the_reloaded_state(tiny_data_dir):
    """For the (linear) tiny plants ``y = C x`` at every sample, recomputed by hand."""
    loaded, _ = load_demos(tiny_data_dir)
    for name in np.unique(loaded.plant):
        plant = load_plant(str(name))
        assert plant.is_linear
        rows = loaded.plant == name
        assert np.all(loaded.order[rows] == plant.order)
        assert np.all(loaded.tag[rows] == plant.tag)
        x = loaded.x[rows]
        np.testing.assert_array_equal(x[..., plant.order :], 0.0)  # zero padding
        c = np.asarray(plant.C, dtype=float)[0]
        y_hand = np.einsum("bkn,n->bk", x[..., : plant.order], c)
        scale = np.abs(y_hand).max()
        assert scale > 0
        np.testing.assert_allclose(loaded.y[rows], y_hand, rtol=0, atol=1e-12 * scale)
        # the response moves towards the step: by the end it is closer to r than at rest
        r = loaded.r[rows]
        assert np.all(np.abs(r[:, -1] - loaded.y[rows][:, -1]) < np.abs(r[:, -1]))
