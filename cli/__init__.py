"""Thin command-line front ends: they parse arguments (tyro) and call library functions."""
