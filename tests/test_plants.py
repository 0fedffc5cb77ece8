"""The plant catalogue: composition, paper matrices, LQI fitness, nonlinear models."""

from __future__ import annotations

import control
import numpy as np
import pytest
from hydra import compose, initialize_config_dir

import generalist_control.common.paths
from generalist_control.common.sections import as_dict
from generalist_control.plants.catalog import plants_from_config
from generalist_control.plants.definition import Plant
from generalist_control.simulation.lqi import LQIController, design_lqi
from generalist_control.simulation.metrics import step_metrics
from generalist_control.simulation.simulate import simulate

NAMES = [
    "mass_spring_damper",
    "damped_oscillator",
    "double_integrator",
    "rlc_circuit",
    "differential_drive",
    "dc_servo",
    "two_tank",
    "coupled_tanks",
    "hvac_two_zone",
    "negative_stiffness",
    "cstr",
    "unstable",
    "boeing747",
    "hydraulic_actuator",
    "auv_yaw",
    "two_mass_spring",
    "crazyflie_altitude",
    "dc_motor_speed",
    "magnetic_levitation",
    "inverted_pendulum_cart",
    "ball_and_beam",
    "quarter_car",
    "flexible_joint",
    "ship_steering",
    "f16_pitch",
]
PAPER = {
    "unstable",
    "cstr",
    "hydraulic_actuator",
    "auv_yaw",
    "boeing747",
    "two_mass_spring",
    "crazyflie_altitude",
}
ABLATION = {
    "double_integrator",
    "crazyflie_altitude",
    "cstr",
    "mass_spring_damper",
    "hvac_two_zone",
}

# The paper's state-space models (Table tab:benchmark_systems), typed in independently.
PAPER_MATRICES = {
    "cstr": (
        [[0, 1], [-5.47, -4.719]],
        [[0], [1]],
        [[3.199, -1.135]],
    ),
    "unstable": (
        [[0, 1], [0, 1]],
        [[0], [1]],
        [[1, 0]],
    ),
    "boeing747": (
        [[-0.32, 0.86], [-0.93, -0.43]],
        [[-0.02], [-1.16]],
        [[1, 0]],
    ),
    "hydraulic_actuator": (
        [[0, 1, 0], [-10, -1.167, 25], [0, 0, -0.8]],
        [[0], [0], [2.4]],
        [[1, 0, 0]],
    ),
    "two_mass_spring": (
        [[0, 0, 1, 0], [0, 0, 0, 1], [-1, 1, 0, 0], [1, -1, 0, 0]],
        [[0], [0], [1], [0]],
        [[0, 1, 0, 0]],
    ),
}

HORIZON = 300  # samples (15 s at dt = 0.05 s)


def _compose(systems: str) -> dict[str, Plant]:
    conf = str(generalist_control.common.paths.conf_dir())
    with initialize_config_dir(conf, version_base="1.3"):
        cfg = compose("config", overrides=[f"systems={systems}"])
    return {p.name: p for p in plants_from_config(as_dict(cfg.systems))}


@pytest.fixture(scope="module")
def plants() -> dict[str, Plant]:
    return _compose("all")


def _step(plant: Plant, amplitude: float, steps: int = HORIZON) -> dict[str, float]:
    tr = simulate(plant, LQIController(plant), np.full((1, steps), amplitude))
    m = step_metrics(tr.t, tr.y, tr.u, tr.r[:, -1])
    out = {k: float(v[0]) for k, v in m.items()}
    out["diverged"] = bool(tr.diverged[0])
    out["x_min"] = (tr.x[0] + plant.x_op).min(axis=0)
    out["u_abs_min"] = float((tr.u[0] + plant.u_op).min())
    return out


def test_the_papers_25_plants_keep_tags_0_to_24_and_a_plant_added_the_next(plants):
    """A plant added to the catalogue (one file, one line in the set) needs no edit here."""
    by_tag = [name for name, _ in sorted(plants.items(), key=lambda kv: kv[1].tag)]
    assert by_tag[:25] == NAMES
    assert sorted(p.tag for p in plants.values()) == list(range(len(plants)))


def test_orders_2_3_4_all_occur(plants):
    orders = [plants[name].order for name in NAMES]
    assert set(orders) == {2, 3, 4}
    assert (orders.count(2), orders.count(3), orders.count(4)) == (12, 7, 6)


def test_metadata_complete(plants):
    for p in plants.values():
        assert p.description and "\n" not in p.description, p.name
        assert p.source, p.name
        assert p.dt == 0.05, p.name
        assert len(p.states) == p.order, p.name
        for sig in (*p.states, p.input_signal, p.output_signal):
            assert sig.name and sig.unit, p.name


@pytest.mark.parametrize("name", sorted(PAPER_MATRICES))
def test_paper_matrices_are_exact(plants, name):
    A, B, C = (np.array(m, dtype=float) for m in PAPER_MATRICES[name])
    p = plants[name]
    np.testing.assert_array_equal(p.A, A)
    np.testing.assert_array_equal(p.B, B)
    np.testing.assert_array_equal(p.C, C)


@pytest.mark.parametrize("name", NAMES)
def test_lqi_design_stable_and_step_settles(plants, name):
    p = plants[name]
    gains = design_lqi(p)
    n = p.order
    Aa = np.zeros((n + 1, n + 1))
    Aa[:n, :n] = p.A
    Aa[n, :n] = -p.C[0]
    Ba = np.append(p.B[:, 0], 0.0)[:, None]
    K = np.append(gains.Kx, gains.Ki)[None, :]
    assert np.all(np.linalg.eigvals(Aa - Ba @ K).real < 0)

    amplitude = 20.0 * p.amplitude_scale
    m = _step(p, amplitude)
    assert not m["diverged"]
    assert np.isfinite(m["settling_time"]) and m["settling_time"] <= 9.0, m["settling_time"]
    assert m["relative_steady_state_error"] < 1e-3


def test_sets_paper_and_ablation():
    assert set(_compose("paper")) == PAPER
    assert set(_compose("ablation")) == ABLATION


def test_auv_yaw_linearisation_matches_analytic_jacobian(plants):
    p = plants["auv_yaw"]
    assert not p.is_linear
    k = p.params
    u0, m = k["u0"], k["m"]
    M = np.array([[m - k["Yvdot"], -k["Yrdot"]], [-k["Nvdot"], k["Izz"] - k["Nrdot"]]])
    # SI / radian model at straight-line motion: cross-flow drag terms have zero slope.
    F = u0 * np.array([[k["Yuv"], k["Yur"] - m], [k["Nuv"], k["Nur"]]])
    G = u0**2 * np.array([k["Yuudr"], k["Nuudr"]])
    Fs, Gs = np.linalg.solve(M, F), np.linalg.solve(M, G)
    # States [v cm/s, r deg/s, psi deg], input delta deg.
    cm, deg = 100.0, 180.0 / np.pi
    A = np.array(
        [
            [Fs[0, 0], Fs[0, 1] * cm / deg, 0.0],
            [Fs[1, 0] * deg / cm, Fs[1, 1], 0.0],
            [0.0, 1.0, 0.0],
        ]
    )
    B = np.array([[Gs[0] * cm / deg], [Gs[1]], [0.0]])
    np.testing.assert_allclose(p.A, A, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(p.B, B, rtol=1e-6, atol=1e-9)
    np.testing.assert_array_equal(p.C, [[0.0, 0.0, 1.0]])
    # Open-loop: integrator, one unstable (Munk moment) and one stable pole.
    poles = np.sort(np.linalg.eigvals(A).real)
    np.testing.assert_allclose(poles, [-2.3344, 0.0, 1.0218], atol=1e-3)


def test_two_tank_linearisation_matches_analytic_jacobian(plants):
    p = plants["two_tank"]
    assert not p.is_linear
    k = p.params
    h1, h2 = p.x_op
    assert h1 > 20 and h2 > 20  # +-20 cm steps keep both levels positive
    # d(a sqrt(2 g h))/dh = a g / sqrt(2 g h)
    d1 = k["a1"] * k["g"] / np.sqrt(2 * k["g"] * h1)
    d2 = k["a2"] * k["g"] / np.sqrt(2 * k["g"] * h2)
    A = np.array([[-d1 / k["A1"], 0.0], [d1 / k["A2"], -d2 / k["A2"]]])
    B = np.array([[1.0 / k["A1"]], [0.0]])
    np.testing.assert_allclose(p.A, A, rtol=1e-6)
    np.testing.assert_allclose(p.B, B, rtol=1e-6)
    assert p.u_op == pytest.approx(k["a2"] * np.sqrt(2 * k["g"] * h2), rel=1e-12)
    assert p.y_op == h2


@pytest.mark.parametrize("name", ["two_tank", "auv_yaw"])
@pytest.mark.parametrize("amplitude", [0.2, -0.2, 1.0, -1.0, 20.0, -20.0])
def test_nonlinear_plants_settle_at_all_amplitudes(plants, name, amplitude):
    p = plants[name]
    m = _step(p, amplitude * p.amplitude_scale)
    assert not m["diverged"]
    assert np.isfinite(m["settling_time"]) and m["settling_time"] <= 9.0
    assert m["relative_steady_state_error"] < 1e-3
    if name == "two_tank":
        assert np.all(m["x_min"] > 0.0)  # no tank runs dry
        assert m["u_abs_min"] > 0.0  # the pump never has to run backwards


def _poles_zeros(p: Plant) -> tuple[np.ndarray, np.ndarray]:
    sys = control.ss(p.A, p.B, p.C, 0)
    return sys.poles(), sys.zeros()


def test_inverted_pendulum_unstable_and_non_minimum_phase(plants):
    p = plants["inverted_pendulum_cart"]
    poles, zeros = _poles_zeros(p)
    assert np.any(poles.real > 0.1)
    assert np.any(zeros.real > 0.1)
    # the same from the transfer function's numerator (leading round-off terms dropped)
    num = np.asarray(control.ss2tf(p.A, p.B, p.C, 0).num[0][0], dtype=float)
    num = num[np.argmax(np.abs(num) > 1e-9 * np.abs(num).max()) :]
    assert np.any(np.roots(num).real > 0.1)


@pytest.mark.parametrize("name", ["magnetic_levitation", "negative_stiffness", "unstable"])
def test_open_loop_unstable_plants(plants, name):
    poles, _ = _poles_zeros(plants[name])
    assert np.any(poles.real > 0.1)


def test_cstr_has_rhp_zero(plants):
    _, zeros = _poles_zeros(plants["cstr"])
    # y / u = (3.199 - 1.135 s) / (s^2 + 4.719 s + 5.47): zero at s = 3.199 / 1.135
    np.testing.assert_allclose(zeros.real.max(), 3.199 / 1.135, rtol=1e-9)


@pytest.mark.parametrize(
    ("u_op", "ok"), [(469.81379290097, True), (469.8138, True), (475.0, False)]
)
def test_equilibrium_check_is_relative(u_op, ok):
    """two_tank's u_op to 7 digits is an equilibrium; 1% off is not (a clear error)."""
    from omegaconf import OmegaConf

    from generalist_control.plants.config import plant_from_config
    from generalist_control.plants.definition import PlantConfigError

    cfg = OmegaConf.to_container(
        OmegaConf.load(generalist_control.common.paths.CONF_DIR / "plants/two_tank.yaml")
    )
    cfg["dynamics"]["u_op"] = u_op
    if ok:
        assert plant_from_config("two_tank", cfg).name == "two_tank"
    else:
        with pytest.raises(PlantConfigError, match="is not an equilibrium"):
            plant_from_config("two_tank", cfg)


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"tag": -3}, "field 'tag' must be a non-negative integer.*got -3"),
        ({"tag": True}, "field 'tag' must be a non-negative integer.*got True"),
        ({"tag": 2.5}, "field 'tag' must be a non-negative integer.*got 2.5"),
        ({"dt": float("inf")}, "field 'dt' contains NaN or inf"),
        ({"dt": "fast"}, "field 'dt' must be a number, got 'fast'"),
        ({"substeps": 2.5}, "field 'substeps' must be an integer >= 1, got 2.5"),
        ({"amplitude_scale": 1e13}, r"'amplitude_scale' has an entry of 1e\+13, beyond \+-1e\+12"),
        ({"lqi": {"Q": [1.0, 1e300, 1.0], "R": 1.0}}, r"'lqi.Q' has an entry of 1e\+300.*rescale"),
        ({"B": [[0.0], [-1e300]]}, r"'B' has an entry of 1e\+300.*rescale"),
    ],
    ids=["negative-tag", "bool-tag", "float-tag", "inf-dt", "text-dt", "float-substeps",
         "huge-scale", "huge-Q", "huge-B"],
)  # fmt: skip
def test_every_number_of_a_plant_file_is_checked_and_the_file_named(changes, match):
    """Each refused at the file check, before the LQI design (scipy's own words for 1e300)."""
    from omegaconf import OmegaConf

    from generalist_control.plants.config import plant_from_config
    from generalist_control.plants.definition import PlantConfigError

    path = generalist_control.common.paths.CONF_DIR / "plants/mass_spring_damper.yaml"
    cfg = {**OmegaConf.to_container(OmegaConf.load(path)), **changes}
    with pytest.raises(PlantConfigError, match=match) as info:
        plant_from_config("mass_spring_damper", cfg, "my/plant.yaml")
    assert str(info.value).startswith("my/plant.yaml: plant 'mass_spring_damper': field")


def test_a_plant_name_with_a_dot_or_a_file_that_is_a_list_is_refused():
    from generalist_control.plants.config import plant_from_config
    from generalist_control.plants.definition import PlantConfigError

    with pytest.raises(PlantConfigError, match=r"splits keys at dots.*e\.g\. my_plant\.yaml"):
        plant_from_config("my.plant", {"tag": 30})
    with pytest.raises(PlantConfigError, match="holds a list, not the mapping of a plant's"):
        plant_from_config("listed", [{"tag": 30}])
