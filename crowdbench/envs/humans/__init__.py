"""Crowd models: how the humans move."""
