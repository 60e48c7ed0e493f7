"""omnire view: the reconstructed scene in the browser (see README.md)."""
