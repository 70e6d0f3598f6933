"""Hydra's configs of hds (package data; `pkg://hds.conf` when a command is imported)."""
