"""vsrd-mi data stage."""
