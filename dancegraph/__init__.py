"""DanceGraph: music in, dance out."""

__version__ = "0.1.0"
