# Palletize: stack four layers of three boxes on a pallet, then go home.
program Palletize version 1.1
use Gripper

speed 100
move 0 -40 30 0 70 0          # home
repeat 4                      # layers
  repeat 3                    # boxes per layer
    call Gripper.pick
    speed 70
    move 60 -20 10 0 60 60    # above the pallet
    move 60 0 -10 0 70 60     # down to the layer
    wait 0.2                  # release
    move 60 -20 10 0 60 60
  end
end
speed 50
move 0 -40 30 0 70 0
