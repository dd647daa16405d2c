"""Widgets of the fieldtool TUI."""
