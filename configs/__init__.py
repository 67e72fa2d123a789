"""Shipped TOML configs (package data): default.toml is the base every other config overlays."""
