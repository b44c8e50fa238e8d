"""Discovery at scale (issue 41): tube descriptors and embeddings, similar tubes, groups of the
unknown set, labels propagated from one tube to its near neighbours."""
