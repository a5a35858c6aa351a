"""stemmap.io"""
