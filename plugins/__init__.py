"""Mitsuba-facing plugin registration for the pmic integrator (see registration.py)."""
