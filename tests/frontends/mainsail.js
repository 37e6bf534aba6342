// Mainsail's own store code in a real Vuex store, fed as Mainsail feeds it.  Only the modules
// the progress / time getters read are registered: printer (Klipper's merged objects plus
// `current_file`, the file's Moonraker metadata) and gui (the settings from Moonraker's
// database namespace `mainsail`).
import Vue from 'vue'
import Vuex from 'vuex'
import { getters as printerGetters } from '@/store/printer/getters'
import { mutations as printerMutations } from '@/store/printer/mutations'
import { getDefaultState as printerDefaultState } from '@/store/printer/index'
import { getters as guiGetters } from '@/store/gui/getters'
import { mutations as guiMutations } from '@/store/gui/mutations'
import { getDefaultState as guiDefaultState } from '@/store/gui/index'

Vue.config.productionTip = false
Vue.config.devtools = false
Vue.use(Vuex)

export const GETTERS = [
  'getPrintPercent',
  'getPrintPercentByFilepositionRelative',
  'getPrintPercentByFilepositionAbsolute',
  'getPrintPercentBySlicer',
  'getPrintPercentByFilament',
  'getEstimatedTimeFile',
  'getEstimatedTimeFilament',
  'getEstimatedTimeSlicer',
  'getEstimatedTimeAvg',
  'getEstimatedTimeETA'
]

export function createStore (database, metadata) {
  const store = new Vuex.Store({
    modules: {
      printer: { namespaced: true, state: printerDefaultState(), getters: printerGetters, mutations: printerMutations },
      gui: { namespaced: true, state: guiDefaultState(), getters: guiGetters, mutations: guiMutations }
    }
  })
  // gui/initStore: the namespace's value from server.database.get_item, merged over the defaults.
  store.commit('gui/setData', database)
  // files/getMetadata for the printing file: clearCurrentFile, then setData { current_file }.
  if (metadata) {
    store.commit('printer/clearCurrentFile', null)
    store.commit('printer/setData', { current_file: metadata })
  }
  return store
}

// printer/getData: the notify_status_update payload (webhooks go to the server module).
export function feed (store, status) {
  const payload = { ...status }
  delete payload.webhooks
  store.commit('printer/setData', payload)
}

export function read (store) {
  const out = {}
  for (const name of GETTERS) out[name] = store.getters['printer/' + name]
  out.displayedPercent = Math.floor(out.getPrintPercent * 100) // StatusPanel.vue, App.vue
  return out
}
