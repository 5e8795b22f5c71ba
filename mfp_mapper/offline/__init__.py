"""Offline tools without a ROS graph: bag replay, simulation, render, evaluate, export."""
