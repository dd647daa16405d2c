"""Matplotlib figures (Agg backend) written as PNG files; no display needed."""
