"""Foundation: errors, SE(3) geometry and Arun's method, trajectory metrics, config serialisation,
process set-up. numpy only."""
