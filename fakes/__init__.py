"""Simulated and replay devices behind the same contracts as the real drivers."""
