"""robocloud's five HTTP services and the framework they share (``services.common``)."""
