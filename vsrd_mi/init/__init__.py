"""vsrd-mi init stage."""
