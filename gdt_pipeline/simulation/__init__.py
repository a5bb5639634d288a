"""Simulated data with ground truth, for tests, benchmarks and ``gdt scene``/``gdt simulate``: the scanner simulator
and the generated scenes (the demo's test scene, the paper's test scene over four epochs, the fuselage section).
The engine and the stages never import this package."""

from .fuselage import make_fuselage_scene
from .objects import scene_objects, write_objects
from .paper_scene import TOLERANCE, EpochFiles, make_paper_test_scene
from .scanner import ScannerSpec, SimulatedScan, simulate_scan, write_scan
from .test_scene import SceneFiles, make_test_scene, simulate_stations

__all__ = ["TOLERANCE", "EpochFiles", "ScannerSpec", "SceneFiles", "SimulatedScan", "make_fuselage_scene",
           "make_paper_test_scene", "make_test_scene", "scene_objects", "simulate_scan", "simulate_stations",
           "write_objects", "write_scan"]
