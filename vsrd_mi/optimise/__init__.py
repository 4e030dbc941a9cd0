"""vsrd-mi optimise stage."""
