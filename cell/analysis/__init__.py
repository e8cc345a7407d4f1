"""Registration, filtering, merging, error map and report."""
