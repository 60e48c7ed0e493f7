"""Periodic Vibration Gaussian baseline plugin for omnire (node type ``pvg``, method ``pvg``)."""
