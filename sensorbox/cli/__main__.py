from sensorbox.cli import run

run()
