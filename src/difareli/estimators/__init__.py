"""difareli.estimators."""
