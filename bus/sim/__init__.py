"""Simulated CiA 402 drives with maxon-style interpolated position mode (pure model + canopen adapter)."""
