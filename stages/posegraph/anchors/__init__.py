"""Survey anchors: vertical ones from the scans' ground against the survey cloud, horizontal ones from the road
markings against the survey's marking mask, checked against each other before they enter the graph."""
