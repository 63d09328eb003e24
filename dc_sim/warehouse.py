"""The simulated warehouse: an occupancy grid and a route through its aisles.

Pure Python, without ROS. The grid is laid out as ``nav_msgs/msg/OccupancyGrid`` lays out its data
(row-major from the bottom row, ``index = x + y * width``) and is deliberately not square, so that
a writer mixing up width and height, or rows and columns, produces a visibly wrong map. Besides free
(0) and occupied (100) cells it has an unknown band (-1) and a few cells of intermediate occupancy
so that a map writer's free/occupied thresholds are exercised.

Layout, in the map frame (m): outer walls enclose x in [-1, 8.5], y in [-1, 5]; the strip east of
the east wall (x > 8.5) is unknown, as outside a mapped building. Three rows of shelves run along x
between x = 1 and x = 6; the route is a loop around the first two rows through the aisles and the
cross-aisles at both ends.
"""

from __future__ import annotations

from dataclasses import dataclass

from dc_sim.kinematics import Pose2D, Waypoint

FREE = 0
OCCUPIED = 100
UNKNOWN = -1

RESOLUTION = 0.05  # m per cell
WIDTH = 200  # cells: 10 m along x
HEIGHT = 120  # cells: 6 m along y
ORIGIN = Pose2D(-1.0, -1.0, 0.0)  # the map-frame pose of the corner of cell (0, 0)

WALL_THICKNESS = 0.1
EAST_WALL_X = 8.4  # its inner face; the wall ends at 8.5 and unknown begins
SHELF_X = (1.0, 6.0)
SHELF_ROWS_Y = ((0.8, 1.2), (2.2, 2.6), (3.6, 4.0))
# Where the localiser starts the odometry frame in the map: the map -> odom transform the simulator
# publishes, hence the robot's start pose in the map.
START = Pose2D(0.5, -0.25, 0.1)
# Cells of partial occupancy (a half-seen pallet in the unused north aisle): map-frame centres of
# cells and their values, one per threshold band a writer may use.
PARTIAL_CELLS = ((2.025, 4.425, 10), (2.075, 4.425, 30), (2.125, 4.425, 50), (2.175, 4.425, 70), (2.225, 4.425, 90))
STOP_S = 3.0


@dataclass(frozen=True)
class Grid:
    """An occupancy grid as nav_msgs/msg/OccupancyGrid carries it."""

    width: int  # cells along x
    height: int  # cells along y
    resolution: float  # m per cell
    origin: Pose2D  # map-frame pose of the outer corner of cell (0, 0)
    data: list[int]  # row-major from the bottom row: index = column + row * width

    def cell(self, x: float, y: float) -> tuple[int, int] | None:
        """Column and row of the cell holding map-frame point (x, y), None outside the grid.

        The origin's yaw is taken as 0, as it is for this warehouse.
        """
        column = int((x - self.origin.x) // self.resolution)
        row = int((y - self.origin.y) // self.resolution)
        if 0 <= column < self.width and 0 <= row < self.height:
            return column, row
        return None

    def value_at(self, x: float, y: float) -> int:
        """Occupancy of the cell holding map-frame point (x, y); unknown outside the grid."""
        cell = self.cell(x, y)
        if cell is None:
            return UNKNOWN
        column, row = cell
        return self.data[column + row * self.width]


def _occupancy(x: float, y: float) -> int:
    """Occupancy of the cell whose centre is map-frame point (x, y), partial cells aside."""
    if x > EAST_WALL_X + WALL_THICKNESS:
        return UNKNOWN
    west, south = ORIGIN.x + WALL_THICKNESS, ORIGIN.y + WALL_THICKNESS
    north = ORIGIN.y + HEIGHT * RESOLUTION - WALL_THICKNESS
    if x < west or y < south or y > north or x > EAST_WALL_X:
        return OCCUPIED
    if SHELF_X[0] <= x <= SHELF_X[1] and any(low <= y <= high for low, high in SHELF_ROWS_Y):
        return OCCUPIED
    return FREE


def warehouse_grid() -> Grid:
    """The warehouse's occupancy grid (a new one per call: its data is a mutable list)."""
    data = [
        _occupancy(ORIGIN.x + (column + 0.5) * RESOLUTION, ORIGIN.y + (row + 0.5) * RESOLUTION)
        for row in range(HEIGHT)
        for column in range(WIDTH)
    ]
    grid = Grid(WIDTH, HEIGHT, RESOLUTION, ORIGIN, data)
    for x, y, value in PARTIAL_CELLS:
        cell = grid.cell(x, y)
        assert cell is not None, "partial cells lie inside the grid"
        data[cell[0] + cell[1] * WIDTH] = value
    return grid


def warehouse_start() -> Pose2D:
    """The robot's start pose in the map frame, which is also the map -> odom transform."""
    return START


def warehouse_route() -> list[Waypoint]:
    """A loop around the first two shelf rows, from :func:`warehouse_start`, stopping in front of shelves.

    Consecutive waypoints (and the last and the first, for looping) are joined by straight segments
    through free space, as a follower that turns in place and drives straight needs.
    """
    return [
        Waypoint(3.5, 0.2, STOP_S),  # south aisle, in front of the first row
        Waypoint(7.2, 0.2, STOP_S),  # east cross-aisle, at the end of the first row
        Waypoint(7.2, 3.1, STOP_S),  # east cross-aisle, at the end of the second row
        Waypoint(3.5, 3.1, STOP_S),  # aisle between the second and third rows
        Waypoint(0.2, 3.1, STOP_S),  # west cross-aisle, at the head of the second row
        Waypoint(0.2, 0.2, STOP_S),  # west cross-aisle, at the head of the first row
    ]
