"""Structured-light sensing: patterns, decoding, triangulation, error model."""
