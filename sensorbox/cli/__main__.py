from sensorbox.cli.main import main

main()
