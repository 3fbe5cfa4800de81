"""The repository's root, for the tests that read its files (they live at different depths)."""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
