"""`mocap live`: the machine's pose frame by frame from cameras as they deliver."""
