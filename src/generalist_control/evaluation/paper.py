"""Figures reported in the paper, the independent reference our reports compare against.

Agyei & Sarhadi, *Generalist AI Control*, Control Engineering Practice 2026: Table 2
(``tab:benchmark_performance``, unit-step metrics of LQI and the Generalist Controller)
and the ablation figures of Section 7.
"""

from __future__ import annotations

from typing import Any

__all__ = ["ABLATION", "TABLE2", "TABLE2_COLUMNS", "TABLE2_METRICS"]

#: Table 2 column label for each of the seven systems, in the paper's order.
TABLE2_COLUMNS = {
    "unstable": "Unst.",
    "cstr": "NMP",
    "hydraulic_actuator": "H.Act",
    "auv_yaw": "Yaw",
    "boeing747": "B-747",
    "two_mass_spring": "TMS",
    "crazyflie_altitude": "Crazyflie",
}

#: Our metric name -> the paper's symbol, in the table's row order.
TABLE2_METRICS = {
    "rise_time": "t_r",
    "overshoot": "M_p",
    "settling_time": "t_s",
    "steady_state_error": "e_ss",
    "ISE": "ISE",
    "ITAE": "ITAE",
    "u_max": "u_max",
}

_ROWS = {  # metric: (LQI row, GC row), columns in TABLE2_COLUMNS order
    "rise_time": (
        (1.75, 1.05, 4.35, 2.50, 1.20, 1.70, 2.15),
        (1.95, 1.05, 3.95, 2.45, 1.40, 1.75, 1.85),
    ),
    "overshoot": ((5.5, 0.4, 0.0, 0.8, 2.3, 11.5, 1.60), (5.4, 0.7, 0.2, 0.4, 2.0, 11.1, 2.00)),
    "settling_time": (
        (5.05, 2.20, 8.15, 4.25, 2.85, 7.25, 4.05),
        (6.35, 2.25, 7.80, 5.10, 2.35, 9.50, 5.55),
    ),
    "steady_state_error": ((0.0,) * 7, (0.0,) * 7),
    "ISE": (
        (1.21, 1.09, 1.40, 1.14, 0.82, 1.88, 0.87),
        (1.28, 1.12, 1.53, 1.17, 0.92, 1.99, 0.79),
    ),
    "ITAE": ((1.8, 0.8, 4.8, 2.2, 0.7, 3.9, 1.4), (2.9, 1.0, 5.0, 4.2, 1.1, 5.1, 2.50)),
    "u_max": (
        (0.73, 1.97, 0.14, 1.10, 1.74, 1.36, 0.08),
        (0.65, 1.96, 0.13, 1.12, 1.58, 1.34, 0.10),
    ),
}

#: TABLE2[controller][system][metric], controller "LQI" or "GC".
TABLE2: dict[str, dict[str, dict[str, float]]] = {
    ctrl: {
        system: {metric: rows[i][j] for metric, rows in _ROWS.items()}
        for j, system in enumerate(TABLE2_COLUMNS)
    }
    for i, ctrl in enumerate(("LQI", "GC"))
}

#: Section 7 figures: final training loss per configuration, parameter counts.
ABLATION: dict[str, dict[str, Any]] = {
    "final_train_loss": {
        "d=32,M=3": 9.43e-4,
        "d=16,M=3": 1.02e-2,
        "d=64,M=3": 4.01e-4,
        "d=32,M=5": 5.87e-4,
    },
    "parameters": {"d=32,M=3": 59_180, "d=64,M=3": 232_000},
}
