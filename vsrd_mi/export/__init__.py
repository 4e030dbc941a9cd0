"""vsrd-mi export stage."""
