"""vsrd-mi scene stage."""
