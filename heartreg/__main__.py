from heartreg.cli import main
import sys
sys.exit(main())
