"""Thin adapters from pipeline artifacts to cobgs library calls, one file per stage."""
