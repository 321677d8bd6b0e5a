"""The leaderboard's constants that an agent's map and the scores depend on."""


class Constants:
    def __init__(self, qualifier: bool = False, testing: bool = False):
        self.map_size = 9 if qualifier else 27  # m
        self.cell_size = 0.15  # m
        self.cell_number = int(self.map_size / self.cell_size)
        self.total_cells = self.cell_number * self.cell_number
        if testing:
            self.max_mission_duration = 30
        elif qualifier:
            self.max_mission_duration = 1 * 3600
        else:
            self.max_mission_duration = 24 * 3600  # s
        self.geometric_map_max_score = 300.0
        self.geometric_map_threshold = 0.05  # m
        self.rock_max_score = 300.0
        self.mapping_productivity_score_rate = (
            self.total_cells / self.max_mission_duration
        )  # cells / s
        self.mapping_productivity_max_score = 250.0
        self.fiducials_max_score = 150.0
