"""stemmap.cloud"""
