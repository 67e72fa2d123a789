"""admc.model"""
