from pipeline.cli import main
from pipeline.parallel import exit_with_parent_from_env

exit_with_parent_from_env()  # a child of `cornermap rebuild` ends with it (pipeline.rebuild.cli)
main()
