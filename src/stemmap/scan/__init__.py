"""stemmap.scan"""
