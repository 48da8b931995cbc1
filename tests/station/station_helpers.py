"""Helpers shared by the station tests."""

from valve_emulator.config import server_from_mapping

PLANT = {"num": [3.0], "den": [10.0, 1.0], "delay": 10.0, "pv_range": [-10.0, 10.0], "units": "kg/m3"}
JSON = {"Content-Type": "application/json"}


def station_config(tick=0.1, noise=0.0):
    plant = {**PLANT, "noise": noise}
    return server_from_mapping({"device": {"tick": tick, "instructor_writes": True}, "loops": [
        {"unit": 1, "name": "FIC101", "valve": {"model": "kano", "S": 5.0, "J": 2.0}, "plant": plant,
         "controller": {"kc": 0.2, "ti": 10.0, "sp": 0.0}},
        {"unit": 2, "name": "HIC102", "valve": {"model": "kano", "S": 3.0, "J": 1.0}, "plant": plant},
    ]})
