"""Agents: TD-MPC2 (baseline) and LNN-TD-MPC2 building blocks (math pieces, planner, world models)."""
