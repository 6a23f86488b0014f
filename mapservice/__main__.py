from mapservice.cli import main
from pipeline.parallel import exit_with_parent_from_env

exit_with_parent_from_env()  # a child a command started ends with it (mapservice.child.run_cornermap)
main()
