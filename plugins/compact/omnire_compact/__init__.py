"""``omnire compact``: a smaller copy of a trained run (see docs/compact.md)."""
