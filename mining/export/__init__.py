"""Products out of the catalogue: `mine export` and `mine render`."""
