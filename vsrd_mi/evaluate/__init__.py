"""vsrd-mi evaluate stage."""
