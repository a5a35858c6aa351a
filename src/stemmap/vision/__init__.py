"""stemmap.vision"""
