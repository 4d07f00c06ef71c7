"""The ``recovery:`` section: when the robot relocalizes itself and when it may move again.

The state machine that uses it is ``robot.control.recovery``.
"""

from __future__ import annotations

from dataclasses import dataclass

from robot.config.ranges import check_fields, flag, integer, number


@dataclass(frozen=True)
class RecoveryConfig:
    enabled: bool = flag(True, "relocalize by itself when the pose is missing, lost or contradicted")
    lost_after: float = number(5.0, 0.1, 120.0, "s", "of quality 'lost' before relocalizing")
    kidnap_frames: int = integer(4, 1, 100, "", "views in a row with every fitted wall rejected ...")
    kidnap_time: float = number(1.0, 0.1, 120.0, "s", "... for at least this long: the robot was moved")
    kidnap_min_walls: int = integer(2, 1, 10, "", "fitted walls a view needs to count toward a kidnap (one wall "
                                    "alone may be a panel standing in front of it)")
    check_frames: int = integer(6, 1, 100, "", "views that may disagree with a saved or operator pose before "
                                "relocalizing")
    confirm_updates: int = integer(3, 1, 100, "", "accepted plane updates after a relocalization before moving")
    retry_period: float = number(2.0, 0.1, 120.0, "s", "between attempts while ambiguous or without an answer")
    auto_resume: bool = flag(True, "resume the mission after confirmation (false: wait for a resume command)")
    turn_in_place: bool = flag(False, "when a relocalization is ambiguous or finds nothing, turn slowly in place "
                               "to view more headings and relocalize again with all views")
    turn_rate: float = number(0.3, 0.05, 1.0, "rad/s", "turn rate of the in-place turn (also capped at "
                              "control.max_yaw_rate)")
    turn_step_deg: float = number(45.0, 10.0, 180.0, "deg", "heading turned between two views")
    max_turn_deg: float = number(360.0, 10.0, 360.0, "deg", "largest heading turned in one relocalization "
                                 "(views at multiples of turn_step_deg up to this, a view at 360 deg repeats the first)")
    move_to_tell_apart: bool = flag(False, "when a relocalization stays ambiguous (after the turn, if any), turn on "
                                    "the spot to face the way and drive a short straight move after which the map "
                                    "predicts different depth for the hypotheses, clear of the walls in every one of "
                                    "them, and relocalize again with all views")
    move_max_distance: float = number(2.0, 0.1, 5.0, "m", "longest such move")
    move_clearance: float = number(0.15, 0.0, 1.0, "m", "kept between the robot's circumscribed circle and every map "
                                   "wall along the move, in every hypothesis (site clutter is the protective stop's)")
    move_speed: float = number(0.1, 0.02, 0.5, "m/s", "speed of the move (also capped at control.max_speed)")
    max_moves: int = integer(2, 1, 5, "", "moves per relocalization trigger (from 2, where no single move tells the "
                             "places apart, a path of two: the first is driven, the next planned from the view there)")

    def __post_init__(self):
        check_fields(self, "recovery")
