"""Reports on a session as a whole."""
