"""admc.stores"""
