"""Benchmarks: each module prints a table (run through `lenslesscam bench ...`)."""
