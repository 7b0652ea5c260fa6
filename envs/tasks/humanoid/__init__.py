"""The humanoid (Unitree G1) tabletop suite: two dexterous hands, side grasps, bimanual tasks."""

from .handover import Handover
from .lift_box import LiftBox
from .open_lid import OpenLid
from .pick_place import HumanoidPickPlace
from .place_in_basket import PlaceInBasket
from .push import HumanoidPush

HUMANOID_TASKS = (HumanoidPickPlace, PlaceInBasket, Handover, LiftBox, HumanoidPush, OpenLid)
