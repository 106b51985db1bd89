"""What every robocloud service shares: settings, errors, auth, logging, metrics, app factory."""
