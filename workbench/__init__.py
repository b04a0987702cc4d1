"""The Articulated Volume Workbench application: CLI, study folders, file I/O."""

__version__ = "0.1.0"
