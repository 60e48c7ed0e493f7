"""Built-in registrations (filled in as the core grows)."""
