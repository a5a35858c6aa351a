"""stemmap.fusion"""
