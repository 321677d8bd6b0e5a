"""Command-line interface (thin: parses arguments, calls the library, prints)."""

from lunarloc.cli.app import app, main

__all__ = ["app", "main"]
