"""stemmap.sim"""
