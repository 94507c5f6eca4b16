"""The method's three stages, one module or package each, and the runner that drives them
(docs/architecture.md)."""
