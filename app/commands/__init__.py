"""Subcommands of the lenslesscam CLI (one module each)."""
