"""admc.cli"""
