"""stemmap.slam"""
