"""descriptors stage."""
