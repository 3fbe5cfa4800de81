"""estop: emergency-stop unit for remote-driven research cars (Python tools)."""

__version__ = "1.0.0"
