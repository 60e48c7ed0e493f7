"""omnire-serve: closed-loop simulation on a reconstructed scene."""
