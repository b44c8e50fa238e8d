"""Discovery: what helps find objects no class names (tube embeddings, descriptors)."""
