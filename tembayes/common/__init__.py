"""Small helpers every stage shares: seed streams, even thinning, version provenance."""
