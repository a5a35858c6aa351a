"""stemmap.harvester"""
