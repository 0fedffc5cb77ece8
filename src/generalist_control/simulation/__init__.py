"""Closed-loop simulation, the LQI experts, metrics, scenarios and the Crazyflie stand-in."""
