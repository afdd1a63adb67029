"""Figures of the lab's studies (the product's report lives in skidkin_ros.report)."""

__all__ = ['estimation']
