"""vsrd-mi bench stage."""
