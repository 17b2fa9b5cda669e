"""Procedural benchmark rooms with exact ground truth (see docs/benchmark_rooms.md)."""
