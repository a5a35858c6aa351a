"""stemmap.viz"""
