"""vsrd-mi render stage."""
