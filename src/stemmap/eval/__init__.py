"""stemmap.eval"""
