"""Shipped weights (package data): manifest.json lists each file with the [model] it was trained as."""
