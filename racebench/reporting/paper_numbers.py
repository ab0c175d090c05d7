"""The paper's own numbers (Sun et al., Tables II-IV), as data: what every regenerated cell is printed beside."""

from __future__ import annotations

# The paper's numbers (Sun et al., Tables II-IV; 10 trials per cell): success rate [%] and lap time [s].
PAPER_SUCCESS: dict[str, dict[str, int]] = {
    "vision-ppo": {"S": 100, "Circle": 100, "J": 100},
    "state-ppo": {"S": 30, "Circle": 20, "J": 30},
    "vision-com": {"S": 30, "Circle": 40, "J": 40},
    "vision-no-gru": {"S": 80, "Circle": 70, "J": 80},
    "vision-no-avoid": {"S": 40, "Circle": 40, "J": 30},
    "vision-one-step": {"S": 0, "Circle": 0, "J": 0},
}
PAPER_LAP_TIME: dict[str, dict[str, float]] = {
    "vision-ppo": {"S": 3.4, "Circle": 3.6, "J": 2.9},
    "state-ppo": {"S": 3.5, "Circle": 3.8, "J": 3.1},
    "vision-com": {"S": 5.4, "Circle": 3.8, "J": 3.9},
}
PAPER_VARIANTS: dict[str, dict[str, int]] = {  # Table IV, vision-ppo
    "Density2": {"S": 100, "Circle": 100, "J": 100},
    "Density3": {"S": 100, "Circle": 100, "J": 100},
    "Density4": {"S": 90, "Circle": 90, "J": 90},
    "Density5": {"S": 80, "Circle": 70, "J": 80},
    "GateShift0.3": {"S": 100, "Circle": 100, "J": 100},
    "GateShift0.5": {"S": 100, "Circle": 100, "J": 100},
    "GateShift0.7": {"S": 90, "Circle": 80, "J": 90},
    "GateShift1.0": {"S": 80, "Circle": 60, "J": 70},
}
