"""fieldtool: river discharge from a surface video (LSPIV) and a surveyed cross-section."""

__version__ = "0.1.0"
