"""Loop closures: candidates between passes on the current estimate, and their verification by ICP."""
