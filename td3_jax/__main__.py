from td3_jax.cli.app import main

main()
