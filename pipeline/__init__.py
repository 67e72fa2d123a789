"""admc.pipeline"""
