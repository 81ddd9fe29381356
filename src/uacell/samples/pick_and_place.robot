# PickAndPlace: take a part from the infeed and put it on the outfeed conveyor.
program PickAndPlace version 2.0
use Gripper

speed 80
move 0 -30 20 0 60 0        # home above the infeed
call Gripper.pick
speed 80
move 90 -30 20 0 60 90      # swing over the outfeed, turning the part
call Gripper.place
move 0 -30 20 0 60 0        # back home
wait 0.5
